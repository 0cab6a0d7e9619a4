"""Study reports: learning curves, a table at the named budgets with published anchors, an
aggregate over tasks, and what each cell cost — as the field reports RL results.

Statistics come from rliable (Agarwal et al., 2021), the field's reporting standard: percentile
bootstrap confidence intervals over seeds per task, and over tasks the interquartile mean (IQM)
with stratified bootstrap CIs and a performance profile. Scores are normalised by 1000, the
maximum return of a dm_control task, to aggregate over tasks.

The report reads the cells' small files (``results/study/<name>/<task>/<variant>/``): a partly
finished study reports what exists and marks what is missing.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from mjx_collo import metrics as metrics_lib
from mjx_collo import study as study_lib
from mjx_collo.study import StudyConfig

MAX_RETURN = 1000.0  # dm_control rewards are in [0, 1] per env step, 1000 steps per episode
REPS = 2000  # bootstrap resamples
FACTS = ("starts_on_feet", "got_up", "fell")  # the task facts a report shows (Env.eval_metrics)


@dataclass
class Series:
    """One variant's runs of one task (a swept variant gives one series per swept value)."""

    label: str
    variant: str = ""  # the variant's name (sections select by it)
    evals: dict[int, np.ndarray] = field(default_factory=dict)  # env step -> returns [seeds]
    wall_s: float = float("nan")
    env_steps: int = 0
    sps_per_run: float = float("nan")
    runs: int = 0
    per_program: int = 0  # runs trained together in one program (all of them, unless in parts)
    platforms: list[str] = field(default_factory=list)
    prior_alone: bool = False  # the same runs acting with their policy prior alone (no cost row)
    # the task's facts of each evaluation (Env.eval_metrics; quadruped: starts on their feet,
    # down starts that got up): env step -> {name: [seeds]}, and the episodes per seed
    facts: dict[int, dict[str, np.ndarray]] = field(default_factory=dict)
    episodes: int = 0

    def at(self, step: int) -> np.ndarray | None:
        return self.evals.get(step)


def _label(variant: study_lib.Variant, run_label: dict) -> str:
    swept = {k: v for k, v in run_label.items() if k != "seed"}
    if not swept:
        return variant.display
    return variant.display + " (" + ", ".join(f"{k}={v:g}" for k, v in swept.items()) + ")"


def load_cell(cell_dir: Path, variant: study_lib.Variant) -> list[Series]:
    """The series of one cell from its small files (none when it has no metrics yet)."""
    metrics = cell_dir / "metrics.jsonl"
    if not metrics.exists():
        return []
    rows, _ = metrics_lib.read_rows(metrics)  # a cut-off last row (a killed run) is left out
    labels_file = cell_dir / "seeds.json"
    n = 1 + max((r["seed"] for r in rows), default=-1)
    labels = (
        json.loads(labels_file.read_text())
        if labels_file.exists()
        else [{"seed": i} for i in range(n)]
    )
    names = [_label(variant, lab) for lab in labels]
    cfg_file = cell_dir / "config.yaml"
    episodes = (
        int(yaml.safe_load(cfg_file.read_text()).get("run", {}).get("eval_episodes", 0))
        if cfg_file.exists()
        else 0
    )
    host = cell_dir / "host.json"
    hosts = json.loads(host.read_text()) if host.exists() else []
    # where it ran: the platform, and on a CPU the model (speeds differ ~2x between VMs); a
    # record from before the model was kept says only "cpu"
    platforms = sorted(
        {
            f"{h.get('platform', '?')}: {h['cpu']}"
            if h.get("platform") == "cpu" and h.get("cpu")
            else h.get("platform", "?")
            for h in hosts
        }
    )
    # the programs that trained the cell: one, or the seed groups of a cell trained in parts
    # (study seeds_per_program; their host.json entries name the seeds)
    seed_of = [int(lab.get("seed", i)) for i, lab in enumerate(labels)]
    programs = {tuple(h["seeds"]) for h in hosts if h.get("seeds")} or {tuple(seed_of)}
    out: dict[str, Series] = {}
    for name in dict.fromkeys(names):
        idx = [i for i, x in enumerate(names) if x == name]
        s = Series(label=name, variant=variant.name, runs=len(idx), platforms=platforms)
        s.evals = _evals(rows, idx, "eval/return")
        # wall time: the programs one after another, each from its first launch to its last row
        walls = [
            max(
                (
                    r["perf/wall_s"]
                    for r in rows
                    if "perf/wall_s" in r and r["seed"] < len(seed_of) and seed_of[r["seed"]] in p
                ),
                default=None,
            )
            for p in programs
        ]
        walls = [w for w in walls if w is not None]
        s.wall_s = sum(walls) if walls else float("nan")
        s.per_program = max(len(p) for p in programs) if len(programs) > 1 else len(idx)
        train = [r for r in rows if r["kind"] == "train" and r["seed"] == idx[0]]
        # where every run has got to (the parts of a cell trained in parts reach it one by one)
        s.env_steps = min(
            max((r["step"] for r in rows if r["kind"] == "train" and r["seed"] == i), default=0)
            for i in idx
        )
        sps = [r["perf/env_steps_per_s"] for r in train if "perf/env_steps_per_s" in r]
        s.sps_per_run = float(np.median(sps)) if sps else float("nan")
        for key in FACTS:
            for step, v in _evals(rows, idx, f"eval/{key}").items():
                s.facts.setdefault(step, {})[key] = v
        s.episodes = episodes
        out[name] = s
        prior = _evals(rows, idx, "eval/return_prior")
        if prior:  # a policy-prior run's evaluations of the prior acting alone, same episodes
            out[name + ", prior alone"] = dataclasses.replace(
                s, label=name + ", prior alone", evals=prior, prior_alone=True
            )
    return list(out.values())


def _evals(rows: list[dict], idx: list[int], key: str) -> dict[int, np.ndarray]:
    """env step -> ``key`` of the runs ``idx`` (steps where every one of them has it)."""
    by_step: dict[int, dict[int, float]] = {}
    for r in rows:
        if r["seed"] in idx and r["kind"] == "eval" and key in r:
            by_step.setdefault(r["step"], {})[r["seed"]] = r[key]
    return {
        k: np.array([v[i] for i in idx]) for k, v in sorted(by_step.items()) if len(v) == len(idx)
    }


def _k(steps: int) -> str:
    """Env steps as the tables show them: 800, 25k, 100k."""
    return f"{steps / 1000:g}k" if steps >= 1000 else str(steps)


@contextlib.contextmanager
def _seeded():
    """Reproducible bootstraps: rliable's StratifiedBootstrap draws its resamples from NumPy's
    global RNG (``update_indices`` calls ``np.random.choice``) whatever ``random_state`` it is
    given, so without this a report's CIs changed each time it was written. The caller's global
    RNG state is restored; arch's "random_state is deprecated" warning (rliable passes it) is
    hidden."""
    state = np.random.get_state()
    np.random.seed(0)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)
            yield
    finally:
        np.random.set_state(state)


def _ci(scores: np.ndarray) -> tuple[float, float, float]:
    """Mean over seeds and its 95% percentile-bootstrap CI (rliable)."""
    from rliable import library as rly

    x = np.asarray(scores, np.float64).reshape(-1, 1)
    if x.shape[0] < 2:
        m = float(x.mean())
        return m, float("nan"), float("nan")
    with _seeded():
        point, ci = rly.get_interval_estimates(
            {"v": x},
            lambda s: np.array([np.mean(s)]),
            reps=REPS,
            random_state=np.random.RandomState(0),
        )
    return float(point["v"][0]), float(ci["v"][0, 0]), float(ci["v"][1, 0])


def _fmt(scores: np.ndarray | None) -> str:
    if scores is None:
        return "—"
    m, lo, hi = _ci(scores)
    if np.isnan(lo):
        return f"{m:.0f} (n=1)"
    return f"{m:.0f} [{lo:.0f}, {hi:.0f}]"


def _score(s: Series, budget: int, target: int) -> str:
    """A table entry: the return at ``budget``; for a cell still training towards it (its target
    is at least ``budget``, its last evaluation before), the last evaluation, named as such, so a
    partial table says how far each run got instead of a bare dash. A cell that trained past a
    budget it never evaluated at (the paper's 25k in a cell evaluated every 10k) shows its last
    evaluation before the budget, named by its step: a reading on no more data than the budget
    allows, never an interpolation."""
    if (read := _reading(s, budget, target)) is None:
        return "—"
    step, note = read
    return _fmt(s.evals[step]) + note


def _reading(s: Series, budget: int, target: int) -> tuple[int, str] | None:
    """The evaluation step a table reads for ``budget`` (see `_score`) and the note that names
    it ("" at the budget itself, " at 80k (partial)" before it); None when there is none."""
    if budget in s.evals:
        return budget, ""
    before = [step for step in s.evals if step < budget]
    if target >= budget and before:
        last = max(before)
        return last, f" at {_k(last)}" + (" (partial)" if s.env_steps < budget else "")
    return None


def _budget_of(cfg: StudyConfig, task: str, budget: int | str) -> int | None:
    return cfg.paper_budgets.get(task) if budget == "paper" else int(budget)


def _plot_curves(task: str, series: list[Series], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for s in series:
        if not s.evals:
            continue
        steps = np.array(sorted(s.evals))
        stats = np.array([_ci(s.evals[k]) for k in steps])
        (line,) = ax.plot(
            steps / 1000, stats[:, 0], marker="o", ms=3, label=f"{s.label} (n={s.runs})"
        )
        if s.runs > 1:
            ax.fill_between(
                steps / 1000, stats[:, 1], stats[:, 2], color=line.get_color(), alpha=0.2
            )
    ax.set_xlabel("env steps (thousands)")
    ax.set_ylabel("eval return")
    ax.set_title(f"{task}: mean and 95% bootstrap CI over seeds")
    ax.grid(alpha=0.3)
    if ax.lines:
        ax.legend(fontsize=8)
    else:
        ax.text(0.5, 0.5, "no evaluations yet", ha="center", va="center", transform=ax.transAxes)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _aggregate(cfg: StudyConfig, data: dict, budget: int, out_dir: Path) -> list[str]:
    """IQM with stratified bootstrap CIs and a performance profile over tasks, for the series
    that have ``budget`` on every task with the same number of runs."""
    from rliable import library as rly
    from rliable import metrics

    scores: dict[str, np.ndarray] = {}
    labels = list(dict.fromkeys(s.label for t in cfg.tasks for s in data.get(t, [])))
    for label in labels:
        cols = []
        for task in cfg.tasks:
            s = next((x for x in data.get(task, []) if x.label == label), None)
            cols.append(None if s is None else s.at(budget))
        if any(c is None for c in cols) or len({len(c) for c in cols}) != 1:
            continue
        scores[label] = np.stack(cols, axis=1) / MAX_RETURN  # [runs, tasks]
    lines = [f"### Aggregate over tasks at {_k(budget)} env steps", ""]
    if not scores:
        return lines + ["No variant has finished every task at this budget yet.", ""]
    with _seeded():
        point, ci = rly.get_interval_estimates(
            scores,
            lambda x: np.array([metrics.aggregate_iqm(x)]),
            reps=REPS,
            random_state=np.random.RandomState(0),
        )
    lines += ["| variant | IQM (normalised return) | 95% CI | runs x tasks |", "|---|---|---|---|"]
    for label in scores:
        lo, hi = ci[label][:, 0]
        r, t = scores[label].shape
        lines.append(f"| {label} | {point[label][0]:.3f} | [{lo:.3f}, {hi:.3f}] | {r} x {t} |")
    taus = np.linspace(0.0, 1.0, 101)
    with _seeded():
        profiles, profile_cis = rly.create_performance_profile(scores, taus, reps=REPS)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from rliable import plot_utils

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    plot_utils.plot_performance_profiles(
        profiles,
        taus,
        performance_profile_cis=profile_cis,
        ax=ax,
        colors=dict(zip(scores, plt.rcParams["axes.prop_cycle"].by_key()["color"], strict=False)),
        xlabel=r"normalised return $\tau$ (return / 1000)",
    )
    ax.legend(list(scores), fontsize=8)
    fig.tight_layout()
    name = f"profile_{_k(budget)}.png"
    fig.savefig(out_dir / name, dpi=110)
    plt.close(fig)
    return lines + ["", f"![performance profile]({out_dir.name}/{name})", ""]


def _task_block(
    cfg: StudyConfig,
    task: str,
    series: list[Series],
    budgets: list[int | str],
    png: Path,
    level: str,
) -> list[str]:
    """One task's learning curves (``png``) and its table at the budgets, with the anchors."""
    _plot_curves(task, series, png)
    lines = [f"{level} {task}", "", f"![{task}]({png.parent.name}/{png.name})", ""]
    heads = [("paper budget" if b == "paper" else _k(int(b))) for b in budgets]
    lines += ["| variant | " + " | ".join(heads) + " |", "|---" * (1 + len(heads)) + "|"]
    targets = {c.variant.name: c.steps for c in study_lib.cells(cfg) if c.task == task}
    for s in series:
        row = [
            _score(s, b, targets.get(s.variant, 0))
            if (b := _budget_of(cfg, task, x)) is not None
            else "—"
            for x in budgets
        ]
        lines.append(f"| {s.label} (n={s.runs}) | " + " | ".join(row) + " |")
    # published anchors: a row each, the score in the column of the budget it was reported at
    # (or, at a budget the table lacks, in the first column with that budget named)
    for a in cfg.anchors:
        if task not in a.scores:
            continue
        cells_ = ["" for _ in heads]
        score = f"{a.scores[task]:g}"
        at = _budget_of(cfg, task, a.budget)
        cols = [i for i, x in enumerate(budgets) if _budget_of(cfg, task, x) == at]
        if cols:
            cells_[cols[0]] = score
        else:
            cells_[0] = f"{score} (at {_k(at)})" if at else score
        lines.append(f"| *{a.name}* | " + " | ".join(cells_) + " |")
    lines.append("")
    lines += _facts_block(cfg, task, series, budgets, targets)
    if "paper" in budgets:
        lines += [
            f"Paper budget for {task}: {cfg.paper_budgets.get(task, '—')} env steps; a cell "
            "with no evaluation there shows its last one before it, named by its step.",
            "",
        ]
    return lines


def _facts_block(
    cfg: StudyConfig,
    task: str,
    series: list[Series],
    budgets: list[int | str],
    targets: dict[str, int],
) -> list[str]:
    """Quadruped's evaluation facts beside its table: how many starts landed on their feet (the
    walk pays ~0 on the back, so a figure is mostly this count until an agent gets up), how many
    of those fell (where logged), and how many down starts got up, over every seed's episodes at
    each budget, read at the same evaluation as the return table (`_reading`)."""
    shown = [s for s in series if s.facts and not s.prior_alone]
    if not shown:
        return []
    heads = [("paper budget" if b == "paper" else _k(int(b))) for b in budgets]
    lines = [
        "Evaluation starts on their feet (torso upright >= 0.5 at reset; *fell*: not up at the "
        "end, where logged) and down starts that got up (upright > 0.8 over the last 100 agent "
        "steps), over all seeds' episodes:",
        "",
        "| variant | " + " | ".join(heads) + " |",
        "|---" * (1 + len(heads)) + "|",
    ]
    for s in shown:
        row = []
        for x in budgets:
            b = _budget_of(cfg, task, x)
            read = _reading(s, b, targets.get(s.variant, 0)) if b is not None else None
            f = s.facts.get(read[0]) if read else None
            if not f or "starts_on_feet" not in f:
                row.append("—")
                continue
            feet, n = int(f["starts_on_feet"].sum()), s.episodes * s.runs
            up = int(f["got_up"].sum()) if "got_up" in f else 0
            # evaluations logged since 2026-12-07 (late) also count the starts on feet that fell
            fell = f" ({int(f['fell'].sum())} fell)" if "fell" in f else ""
            row.append(
                (
                    f"{feet} of {n} on feet{fell}, {up} of {n - feet} got up"
                    if n
                    else f"{feet}{fell}, {up}"
                )
                + read[1]
            )
        lines.append(f"| {s.label} | " + " | ".join(row) + " |")
    return lines + [""]


def _shown(path: Path) -> str:
    """``path`` relative to the working directory when it lies below it (a committed report
    names ``results/study/<name>``, not the machine it was made on)."""
    try:
        return str(Path(path).resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def write(name: str, cfg: StudyConfig, results: Path, out_md: Path) -> Path:
    """Write ``out_md`` and its PNGs (in ``<out_md stem>/``) from the cells under ``results``."""
    out_dir = out_md.parent / out_md.stem
    out_dir.mkdir(parents=True, exist_ok=True)
    cells = study_lib.cells(cfg)
    data: dict[str, list[Series]] = {}
    missing = []
    cost_rows = []
    for cell in cells:
        series = load_cell(Path(results) / cell.task / cell.variant.name, cell.variant)
        data.setdefault(cell.task, []).extend(series)
        reached = max((s.env_steps for s in series), default=0)
        runs = sum(s.runs for s in series if not s.prior_alone)
        if reached < cell.steps:
            # a cell trained in parts: the first part's progress, the other parts not begun
            whole = study_lib.runs_per_cell(cell)
            started = f", {runs} of {whole} runs started" if 0 < runs < whole else ""
            missing.append(f"{cell.key}: {_k(reached)} of {_k(cell.steps)} env steps{started}")
        elif runs < study_lib.runs_per_cell(cell):  # a cell trained in parts, some not yet
            missing.append(f"{cell.key}: {runs} of {study_lib.runs_per_cell(cell)} runs")
        for s in series:
            if s.env_steps and not s.prior_alone:
                cost_rows.append(
                    f"| {cell.task} | {s.label} | {s.runs} | {_k(s.env_steps)} | "
                    f"{s.wall_s / 60:.0f} | {s.sps_per_run:.1f} | {s.sps_per_run * s.per_program:.1f} | "
                    f"{'; '.join(s.platforms) or '?'} |"
                )
    partial = bool(missing)
    lines = [f"# Study: {name}" + (" (partial)" if partial else ""), ""]
    if cfg.description:
        lines += [cfg.description.strip(), ""]
    lines += [
        f"Made by `make study STUDY={name}` and `make report STUDY={name}` from the cells' "
        f"metrics in `{_shown(results)}`. {cfg.seeds} seeds per cell; eval return is the mean of the "
        "run's deterministic evaluation episodes; brackets are 95% percentile-bootstrap CIs over "
        "seeds (rliable).",
        "",
    ]
    if any(s.prior_alone for ss in data.values() for s in ss):
        lines += [
            "A row or curve named *..., prior alone* is the same runs acting with their policy "
            "prior alone (its rollout is the plan) on the same evaluation episodes, logged beside "
            "every evaluation as `eval/return_prior`: what the plan adds to its start.",
            "",
        ]
    if partial:
        lines += (
            ["**Partial:** these cells have not finished:", ""] + [f"- {m}" for m in missing] + [""]
        )

    budgets: list[int | str] = list(cfg.budgets or [cfg.steps])
    if cfg.paper_budgets:
        budgets.append("paper")
    if cfg.sections:
        for sec in cfg.sections:
            chosen = {v.name for v in cfg.variants if sec.name in v.sections}
            lines += [f"## {sec.title}", ""]
            if sec.paper:
                lines += [f"**The paper:** {sec.paper}", ""]
            lines += [
                f"**Here:** {sec.finding or 'to be written when the cells have finished.'}",
                "",
            ]
            for task in cfg.tasks:
                series = [x for x in data.get(task, []) if x.variant in chosen]
                if any(c.task == task and c.variant.name in chosen for c in cells):
                    png = out_dir / f"{sec.name}_{task}.png"
                    lines += _task_block(cfg, task, series, budgets, png, level="###")
    else:
        for task in cfg.tasks:
            png = out_dir / f"{task}.png"
            lines += _task_block(cfg, task, data.get(task, []), budgets, png, level="##")

    lines += ["## Aggregate", ""]
    for b in cfg.budgets or [cfg.steps]:
        lines += _aggregate(cfg, data, int(b), out_dir)
    if cfg.anchors:
        lines += (
            ["## Anchors", ""] + [f"- *{a.name}*: {a.note}" for a in cfg.anchors if a.note] + [""]
        )
    lines += [
        "## Cost",
        "",
        "Wall time from the cell's first launch to its last row (compiles and evaluations "
        "included; a cell trained in parts, its seeds a few at a time, adds its programs' "
        "times); env steps/s of a steady training chunk, per run and for the runs that train "
        "together in one program (all of the cell's, unless it trained in parts).",
        "",
        "| task | variant | runs | env steps | wall min | env steps/s per run | env steps/s per program | ran on |",
        "|---|---|---|---|---|---|---|---|",
        *cost_rows,
        "",
    ]
    if cfg.notes:
        lines += ["## Notes", ""] + [f"- {n}" for n in cfg.notes] + [""]
    out_md.parent.mkdir(parents=True, exist_ok=True)
    out_md.write_text("\n".join(lines))
    return out_md

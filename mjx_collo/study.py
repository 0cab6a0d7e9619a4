"""Studies: a grid of tasks x variants x seeds, each cell an ordinary run directory.

A study config (``configs/study/<name>.yaml``) names the grid; ``make study STUDY=<name>`` trains
its cells one after another (the seeds of a cell vmapped in one program, by ``train.py``), and
``make report STUDY=<name>`` (:mod:`mjx_collo.report`) turns the cells' metrics into a report.

Re-running a study resumes its unfinished cell and skips the finished ones: a cell is finished
when its run directory holds a checkpoint at the cell's last env step, or when its committed record
(``results/study/<name>/<task>/<variant>/``) holds the final evaluation of every run, trained with
the cell's config. The second lets a study go on from a fresh clone or a wiped scratch disk
without retraining what the repository already records. The resolved study config
is stored in the study's root on its first run; a later run with a different config is refused,
naming the keys that differ (a changed config would mix cells trained under two designs); edits to
the report's footnotes, description, anchors and variant labels are taken, and so is a grid that
only grows (new variants or tasks: the cells trained so far stay what they were).

After each cell, and before it starts, the cell's small files (``config.yaml``, ``metrics.jsonl``,
``seeds.json``, ``host.json``) are copied to ``results/study/<name>/<task>/<variant>/``, the
committed record the report reads.

A variant with ``seeds_per_program: k`` trains its cells' seeds k at a time, each group a
program and run directory of its own (``<cell>/seed0``, ``<cell>/seeds2-3``): the same seeds
with the same keys (``train.py --first-seed``), in pieces short enough for one sitting. A
piece is skipped once its seeds' final evaluations are in the committed record, whose files
merge the pieces (``host.json`` entries name the seeds each launch trained).
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path
from typing import Literal, NamedTuple

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from mjx_collo import config as config_lib

ROOT = Path(__file__).resolve().parent.parent
STUDY_DIR = ROOT / "configs" / "study"
SMALL_FILES = ("config.yaml", "metrics.jsonl", "seeds.json", "host.json")


class StudyError(ValueError):
    """A study that cannot run as asked; the message names the problem and the fix."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Variant(_Strict):
    """One method setting: a method plus optional presets, overrides and a float sweep."""

    name: str = Field(description="directory-safe id, e.g. collodreamer")
    label: str | None = Field(None, description="display name in the report (default: name)")
    method: str
    presets: list[str] = []
    overrides: list[str] = []
    sweep: str | None = Field(None, description='one-compile float sweep, "key=v1,v2"')
    budget: Literal["steps", "paper"] = Field(
        "steps", description="train for the study's steps, or the paper's per-task budget only"
    )
    tasks: list[str] | None = Field(None, description="the study's tasks this runs on (all)")
    sections: list[str] = Field([], description="report sections that show this variant")
    seeds_per_program: int | None = Field(
        None,
        ge=1,
        description="train a cell's seeds this many at a time, each group its own program and "
        "run directory (a cell longer than one sitting); none: all seeds in one program",
    )

    @field_validator("name")
    @classmethod
    def _safe(cls, v: str) -> str:
        if not re.fullmatch(r"[A-Za-z0-9_.-]+", v):
            raise ValueError(f"variant name {v!r} must be letters, digits, '_', '-' or '.'")
        return v

    @property
    def display(self) -> str:
        return self.label or self.name


class Anchor(_Strict):
    """Published scores shown beside ours: eval return per task at ``budget`` env steps."""

    name: str
    budget: int | Literal["paper"]
    scores: dict[str, float]
    note: str = ""


class Section(_Strict):
    """A part of the report comparing some variants (an ablation: one of the paper's figures)."""

    name: str
    title: str
    paper: str = Field("", description="the paper's finding, one sentence")
    finding: str = Field("", description="ours, written once the cells have finished")


class StudyConfig(_Strict):
    description: str = ""
    tasks: list[str]
    variants: list[Variant]
    seeds: int = Field(3, ge=1)
    steps: int = Field(100_000, gt=0)
    eval_every: int | None = Field(None, gt=0)
    overrides: list[str] = Field([], description="dotted overrides for every cell")
    budgets: list[int] = Field([], description="env steps read into the report's table")
    paper_budgets: dict[str, int] = Field({}, description="the paper's budget per task")
    anchors: list[Anchor] = []
    notes: list[str] = Field([], description="footnotes printed under the report's table")
    sections: list[Section] = Field(
        [], description="report sections (each shows the variants that name it); none: one table"
    )


class Cell(BaseModel):
    """One (task, variant) of a study."""

    model_config = ConfigDict(frozen=True)

    task: str
    variant: Variant
    seeds: int
    steps: int
    overrides: list[str]

    @property
    def key(self) -> str:
        return f"{self.task}/{self.variant.name}"


def load(name_or_path: str) -> tuple[str, StudyConfig]:
    """(study name, validated config) of ``configs/study/<name>.yaml`` or a YAML path."""
    path = Path(name_or_path)
    if path.suffix not in (".yaml", ".yml"):
        path = STUDY_DIR / f"{name_or_path}.yaml"
    if not path.exists():
        known = ", ".join(sorted(p.stem for p in STUDY_DIR.glob("*.yaml")))
        raise StudyError(f"no study config {path}; studies in {STUDY_DIR}: {known}")
    try:
        raw = config_lib.read_yaml(path)
    except config_lib.ConfigError as e:
        raise StudyError(str(e)) from None
    try:
        cfg = StudyConfig.model_validate(raw)
    except ValidationError as e:
        err = e.errors()[0]
        where = ".".join(str(x) for x in err["loc"])
        raise StudyError(f"{path}: {where}: {err['msg']}") from None
    _check(path, cfg)
    return path.stem, cfg


def _check(path: Path, cfg: StudyConfig) -> None:
    """Everything that can be checked without training: tasks, methods, presets and overrides
    resolve to valid run configs, and every paper-budget variant has a budget for every task."""
    import envs

    names = [v.name for v in cfg.variants]
    if len(set(names)) != len(names):
        raise StudyError(f"{path}: variant names must be unique, got {names}")
    sections = {sec.name for sec in cfg.sections}
    for v in cfg.variants:
        if v.tasks is not None and not set(v.tasks) <= set(cfg.tasks):
            extra = sorted(set(v.tasks) - set(cfg.tasks))
            raise StudyError(f"{path}: variant {v.name} names tasks {extra} the study lacks")
        if set(v.sections) - sections:
            unknown = sorted(set(v.sections) - sections)
            raise StudyError(
                f"{path}: variant {v.name} names sections {unknown}; define them under sections:"
            )
        if v.seeds_per_program and v.sweep:
            raise StudyError(
                f"{path}: variant {v.name} has a sweep and seeds_per_program; a sweep's runs "
                "train in one program, so drop seeds_per_program"
            )
    for task in cfg.tasks:
        try:
            envs.canonical(task)
        except envs.UnknownTaskError as e:
            raise StudyError(f"{path}: {e}") from None
    from mjx_collo import trainer

    for cell in cells(cfg):
        try:
            trainer.validate(run_config(cell))  # what train.py refuses before compiling
        except config_lib.ConfigError as e:
            raise StudyError(f"{path}: cell {cell.key}: {e}") from None


def cells(cfg: StudyConfig) -> list[Cell]:
    """The grid in run order: task by task, variants in the config's order."""
    out = []
    for task in cfg.tasks:
        for v in cfg.variants:
            if v.tasks is not None and task not in v.tasks:
                continue
            if v.budget == "paper":
                if task not in cfg.paper_budgets:
                    raise StudyError(
                        f"variant {v.name} trains at the paper's budget, but paper_budgets has "
                        f"none for {task}: add paper_budgets.{task}"
                    )
                steps = cfg.paper_budgets[task]
            else:
                steps = cfg.steps
            overrides = list(cfg.overrides)
            if cfg.eval_every is not None:
                overrides.append(f"run.eval_every={cfg.eval_every}")
            overrides += v.overrides
            out.append(
                Cell(task=task, variant=v, seeds=cfg.seeds, steps=steps, overrides=overrides)
            )
    return out


def run_config(cell: Cell) -> config_lib.Config:
    """The run config a cell trains with (what ``train.py`` builds from :func:`train_args`)."""
    overrides = cell.overrides + [f"run.steps={cell.steps}"]
    return config_lib.load(
        task=cell.task,
        method=cell.variant.method,
        presets=cell.variant.presets,
        overrides=overrides,
    )


def cell_dir(root: Path, cell: Cell) -> Path:
    return Path(root) / cell.task / cell.variant.name


class Part(NamedTuple):
    """The seeds ``first .. first + seeds - 1`` of a cell, trained as one program in ``dir``."""

    first: int
    seeds: int
    dir: Path
    name: str  # "" for a cell trained whole

    @property
    def labels(self) -> list[int]:
        return list(range(self.first, self.first + self.seeds))


def parts(root: Path, cell: Cell) -> list[Part]:
    """The programs that train the cell: one (in the cell's directory) unless its variant sets
    ``seeds_per_program`` below the study's seeds."""
    k = cell.variant.seeds_per_program
    top = cell_dir(root, cell)
    if not k or k >= cell.seeds:
        return [Part(0, cell.seeds, top, "")]
    out = []
    for a in range(0, cell.seeds, k):
        n = min(k, cell.seeds - a)
        name = f"seed{a}" if n == 1 else f"seeds{a}-{a + n - 1}"
        out.append(Part(a, n, top / name, name))
    return out


def train_args(cell: Cell, run_dir: Path, part: Part | None = None) -> list[str]:
    """``train.py`` arguments that train (or resume) the cell (or its ``part``) in ``run_dir``."""
    seeds = str(part.seeds) if part else str(cell.seeds)
    args = ["--env", cell.task, "--method", cell.variant.method, "--seeds", seeds]
    if part and part.first:
        args += ["--first-seed", str(part.first)]
    args += ["--steps", str(cell.steps), "--run", str(run_dir), "--no-progress"]
    for p in cell.variant.presets:
        args += ["--preset", p]
    if cell.variant.sweep:
        args += ["--sweep", cell.variant.sweep]
    return args + list(cell.overrides)


def checkpoint_steps(run_dir: Path) -> list[int]:
    ckpt = Path(run_dir) / "checkpoints"
    if not ckpt.is_dir():
        return []
    return sorted(int(p.name) for p in ckpt.iterdir() if p.name.isdigit())


def part_finished(part: Part, cell: Cell) -> bool:
    """A checkpoint at (or past) the cell's last env step exists in the part's directory."""
    steps = checkpoint_steps(part.dir)
    return bool(steps) and steps[-1] >= cell.steps


def is_finished(root: Path, cell: Cell) -> bool:
    """Every program of the cell holds a checkpoint at (or past) the cell's last env step."""
    return all(part_finished(p, cell) for p in parts(root, cell))


def runs_per_cell(cell: Cell) -> int:
    """Seeds x swept values: the runs one cell trains in one program."""
    n = cell.seeds
    if cell.variant.sweep:
        for values in config_lib.parse_sweep(cell.variant.sweep, run_config(cell)).values():
            n *= len(values)
    return n


def _same_config(cfg_file: Path, cell: Cell) -> bool:
    """``cfg_file`` (a run's config.yaml) is the config the cell trains with now; keys inert for
    the run do not count."""
    if not cfg_file.exists():
        return False
    try:
        saved = config_lib.build(config_lib.complete_saved(yaml.safe_load(cfg_file.read_text())))
        return not config_lib.diff(saved, run_config(cell))
    except (yaml.YAMLError, config_lib.ConfigError, AttributeError, TypeError):
        return False


def _read_rows(path: Path) -> list[dict]:
    """A metrics file's whole rows (a torn or bad line is left out: a record is read, not
    repaired, here)."""
    rows = []
    for line in path.read_text().splitlines() if path.exists() else []:
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return rows


def _seed_of(labels_file: Path, rows: list[dict]) -> list[int]:
    """Run index -> seed, from ``seeds.json`` (the index itself without one)."""
    try:
        labels = json.loads(labels_file.read_text()) if labels_file.exists() else []
    except (OSError, json.JSONDecodeError):
        labels = []
    n = max([len(labels)] + [r.get("seed", -1) + 1 for r in rows])
    return [int(labels[i].get("seed", i)) if i < len(labels) else i for i in range(n)]


def recorded_finished(results: Path, cell: Cell, seeds: list[int] | None = None) -> bool:
    """The committed record of the cell holds the evaluation at the cell's last env step of every
    run (or of the seeds ``seeds``: one program of a cell trained in parts), and was trained
    with the config the cell would train with now."""
    d = Path(results) / cell.task / cell.variant.name
    if not _same_config(d / "config.yaml", cell):
        return False
    rows = _read_rows(d / "metrics.jsonl")
    final = {r["seed"] for r in rows if r.get("kind") == "eval" and r.get("step", -1) >= cell.steps}
    if seeds is None:
        return len(final) >= runs_per_cell(cell)
    seed_of = _seed_of(d / "seeds.json", rows)
    return set(seeds) <= {seed_of[i] for i in final}


def status(root: Path, cfg: StudyConfig, results: Path | None = None) -> dict[str, str]:
    """Per cell key: ``finished``, ``finished (committed record)``, ``partial (<step> env
    steps)`` or ``not started``."""
    out = {}
    for cell in cells(cfg):
        if is_finished(root, cell):
            out[cell.key] = "finished"
        elif results is not None and recorded_finished(results, cell):
            out[cell.key] = "finished (committed record)"
        elif len(parts(root, cell)) == 1:
            steps = checkpoint_steps(cell_dir(root, cell))
            out[cell.key] = f"partial ({steps[-1]} env steps)" if steps else "not started"
        else:
            states = []
            for p in parts(root, cell):
                steps = checkpoint_steps(p.dir)
                if part_finished(p, cell):
                    states.append(f"{p.name} finished")
                elif results is not None and recorded_finished(results, cell, p.labels):
                    states.append(f"{p.name} finished (committed record)")
                else:
                    states.append(
                        f"{p.name} " + (f"{steps[-1]} env steps" if steps else "not started")
                    )
            started = [x for x in states if not x.endswith("not started")]
            out[cell.key] = "partial (" + ", ".join(states) + ")" if started else "not started"
    return out


# Study fields that only shape the report: editing them (a new footnote, an anchor column) changes
# no cell, so a running study takes the edit instead of refusing it.
REPORT_ONLY = ("description", "notes", "anchors")


def _training(pinned: dict) -> dict:
    """A study config less what only the report reads (:data:`REPORT_ONLY`, variant labels)."""
    out = {k: v for k, v in pinned.items() if k not in REPORT_ONLY}
    # how a cell's seeds group into programs does not change what they train
    out["variants"] = [
        {k: v for k, v in var.items() if k not in ("label", "seeds_per_program")}
        for var in pinned.get("variants", [])
    ]
    return out


def _grows(theirs: dict, mine: dict) -> list[str] | None:
    """What ``mine`` adds to the pinned ``theirs`` when it only grows the grid: new variants, new
    tasks, and nothing else changed (every pinned variant as it was, the same seeds, steps and
    overrides), so that no cell trained so far would train differently. None otherwise."""
    grid = ("tasks", "variants")
    if {k: v for k, v in theirs.items() if k not in grid} != {
        k: v for k, v in mine.items() if k not in grid
    }:
        return None
    if not set(theirs.get("tasks", [])) <= set(mine.get("tasks", [])):
        return None
    new = {v["name"]: v for v in mine.get("variants", [])}
    if any(new.get(v["name"]) != v for v in theirs.get("variants", [])):
        return None
    old = {v["name"] for v in theirs.get("variants", [])}
    added = [f"variant {n}" for n in new if n not in old]
    added += [f"task {t}" for t in mine.get("tasks", []) if t not in theirs.get("tasks", [])]
    return added or None


def pin_config(root: Path, cfg: StudyConfig) -> list[str]:
    """Store the study config in ``root`` on first use; refuse a different one later. Taken and
    stored: edits to the report-only fields (:data:`REPORT_ONLY`, variant labels), and a grid
    that only grows (new variants or tasks beside unchanged ones: the cells trained so far stay
    valid). Returns what the grid gained (empty when nothing did)."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    pinned = root / "study.yaml"
    mine = cfg.model_dump(mode="json")
    if not pinned.exists():
        pinned.write_text(yaml.safe_dump(mine, sort_keys=False))
        return []
    theirs = yaml.safe_load(pinned.read_text())
    if theirs == mine:
        return []
    a = config_lib.flatten(_training(theirs))
    b = config_lib.flatten(_training(mine))
    added = [] if a == b else _grows(_training(theirs), _training(mine))
    if added is not None:
        pinned.write_text(yaml.safe_dump(mine, sort_keys=False))
        return added
    diffs = [
        f"{k}: {a.get(k)!r} -> {b.get(k)!r}"
        for k in sorted(set(a) | set(b))
        if a.get(k) != b.get(k)
    ]
    shown = "; ".join(diffs[:6]) + (f"; ... ({len(diffs)} in all)" if len(diffs) > 6 else "")
    raise StudyError(
        f"the study in {root} was started with a different config ({shown}); finish it with its "
        f"own config ({pinned}), or give the changed study another RUN= directory (adding "
        "variants or tasks is taken; changing or removing them is not)"
    )


def collect(root: Path, cell: Cell, results: Path) -> Path | None:
    """Copy the cell's small files to ``results/<task>/<variant>/``; None if it has none yet. A
    cell trained in parts merges into the record: each part's seeds replace their rows there, and
    the seeds recorded earlier (by a part trained on another machine) are kept, and so are a
    part's recorded rows when its run directory here is behind them."""
    dst = Path(results) / cell.task / cell.variant.name
    ps = parts(root, cell)
    if len(ps) == 1:
        src = ps[0].dir
        files = [src / f for f in SMALL_FILES if (src / f).exists()]
        if not files:
            return None
        dst.mkdir(parents=True, exist_ok=True)
        for f in files:
            shutil.copy2(f, dst / f.name)
        return dst
    present = [p for p in ps if (p.dir / "metrics.jsonl").exists()]
    if not present:
        return None
    rows: dict[int, list[dict]] = {}  # seed -> its rows
    hosts: list[dict] = []
    if _same_config(dst / "config.yaml", cell):  # what the record holds of other parts
        old = _read_rows(dst / "metrics.jsonl")
        seed_of = _seed_of(dst / "seeds.json", old)
        for r in old:
            rows.setdefault(seed_of[r["seed"]], []).append(r)
        for h in _read_json(dst / "host.json"):
            hosts.append({**h, "seeds": h.get("seeds", sorted(rows))})
    for p in present:
        mine = _read_rows(p.dir / "metrics.jsonl")
        seed_of = _seed_of(p.dir / "seeds.json", mine)
        recorded = max((r["step"] for s in p.labels for r in rows.get(s, [])), default=-1)
        if not part_finished(p, cell) and max((r["step"] for r in mine), default=-1) < recorded:
            continue  # a copy left behind on this machine: the record is further along
        for s in p.labels:
            rows.pop(s, None)
        for r in mine:
            rows.setdefault(seed_of[r["seed"]], []).append(r)
        hosts = [
            {**h, "seeds": [s for s in h["seeds"] if s not in p.labels]}
            for h in hosts
            if set(h["seeds"]) - set(p.labels)
        ]
        hosts += [{**h, "seeds": p.labels} for h in _read_json(p.dir / "host.json")]
    order = sorted(rows)
    index = {s: i for i, s in enumerate(order)}
    merged = [{**r, "seed": index[s]} for s in order for r in rows[s]]
    merged.sort(key=lambda r: (r["step"], r["kind"] != "train", r["seed"]))
    dst.mkdir(parents=True, exist_ok=True)
    for p in present:
        if (p.dir / "config.yaml").exists():
            shutil.copy2(p.dir / "config.yaml", dst / "config.yaml")
            break
    _write(dst / "metrics.jsonl", "".join(json.dumps(r) + "\n" for r in merged))
    _write(dst / "seeds.json", json.dumps([{"seed": s} for s in order], indent=1))
    _write(dst / "host.json", json.dumps(hosts, indent=1))
    return dst


def _read_json(path: Path) -> list:
    try:
        return json.loads(path.read_text()) if path.exists() else []
    except (OSError, json.JSONDecodeError):
        return []


def _write(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)

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
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path
from typing import Literal

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


def train_args(cell: Cell, run_dir: Path) -> list[str]:
    """``train.py`` arguments that train (or resume) the cell in ``run_dir``."""
    args = ["--env", cell.task, "--method", cell.variant.method, "--seeds", str(cell.seeds)]
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


def is_finished(root: Path, cell: Cell) -> bool:
    """A checkpoint at (or past) the cell's last env step exists."""
    steps = checkpoint_steps(cell_dir(root, cell))
    return bool(steps) and steps[-1] >= cell.steps


def runs_per_cell(cell: Cell) -> int:
    """Seeds x swept values: the runs one cell trains in one program."""
    n = cell.seeds
    if cell.variant.sweep:
        for values in config_lib.parse_sweep(cell.variant.sweep, run_config(cell)).values():
            n *= len(values)
    return n


def recorded_finished(results: Path, cell: Cell) -> bool:
    """The committed record of the cell holds every run's evaluation at the cell's last env step,
    and was trained with the config the cell would train with now."""
    d = Path(results) / cell.task / cell.variant.name
    cfg_file, metrics = d / "config.yaml", d / "metrics.jsonl"
    if not (cfg_file.exists() and metrics.exists()):
        return False
    try:
        saved = config_lib.build(config_lib.complete_saved(yaml.safe_load(cfg_file.read_text())))
        if config_lib.diff(saved, run_config(cell)):  # keys inert for the run do not count
            return False
    except (yaml.YAMLError, config_lib.ConfigError, AttributeError, TypeError):
        return False
    final = 0
    for line in metrics.read_text().splitlines():
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue
        if row.get("kind") == "eval" and row.get("step", -1) >= cell.steps:
            final += 1
    return final >= runs_per_cell(cell)


def status(root: Path, cfg: StudyConfig, results: Path | None = None) -> dict[str, str]:
    """Per cell key: ``finished``, ``finished (committed record)``, ``partial (<step> env
    steps)`` or ``not started``."""
    out = {}
    for cell in cells(cfg):
        steps = checkpoint_steps(cell_dir(root, cell))
        if steps and steps[-1] >= cell.steps:
            out[cell.key] = "finished"
        elif results is not None and recorded_finished(results, cell):
            out[cell.key] = "finished (committed record)"
        elif steps:
            out[cell.key] = f"partial ({steps[-1]} env steps)"
        else:
            out[cell.key] = "not started"
    return out


# Study fields that only shape the report: editing them (a new footnote, an anchor column) changes
# no cell, so a running study takes the edit instead of refusing it.
REPORT_ONLY = ("description", "notes", "anchors")


def _training(pinned: dict) -> dict:
    """A study config less what only the report reads (:data:`REPORT_ONLY`, variant labels)."""
    out = {k: v for k, v in pinned.items() if k not in REPORT_ONLY}
    out["variants"] = [
        {k: v for k, v in var.items() if k != "label"} for var in pinned.get("variants", [])
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
    """Copy the cell's small files to ``results/<task>/<variant>/``; None if it has none yet."""
    src = cell_dir(root, cell)
    files = [src / f for f in SMALL_FILES if (src / f).exists()]
    if not files:
        return None
    dst = Path(results) / cell.task / cell.variant.name
    dst.mkdir(parents=True, exist_ok=True)
    for f in files:
        shutil.copy2(f, dst / f.name)
    return dst

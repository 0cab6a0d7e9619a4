"""Run or report a study: ``make study STUDY=<name> [RUN=<dir>]``, ``make report STUDY=<name>``.

A study (``configs/study/<name>.yaml``) is a grid of tasks x variants; each cell is an ordinary
run directory under ``runs/study/<name>/<task>/<variant>`` trained by ``train.py`` (its seeds
vmapped in one program), the cells one after another. Re-running resumes the unfinished cell and
skips finished ones. The cells' small files go to ``results/study/<name>/`` as they finish, and
the report to ``docs/results/<name>.md``.

Ctrl-C (or SIGTERM) stops the cell in training after its checkpoint; the study exits with 130
(143) and the same command resumes it.
"""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("action", choices=("run", "report", "status"))
    p.add_argument("study", help="name in configs/study/ or a path to a study YAML")
    p.add_argument("--root", default=None, help="run directories (default runs/study/<name>)")
    p.add_argument("--results", default=None, help="small files (default results/study/<name>)")
    p.add_argument("--out", default=None, help="report (default docs/results/<name>.md)")
    p.add_argument("--max-cells", type=int, default=None, help="train at most N cells, then stop")
    p.add_argument(
        "--only",
        default=None,
        help="train only these variants and/or tasks (comma-separated names), e.g. latco,dreamer",
    )
    p.add_argument("--no-report", action="store_true", help="do not write the report at the end")
    return p.parse_args(argv)


class Stop:
    """SIGINT/SIGTERM: remember it and pass it on to the cell in training (which checkpoints)."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self.child: subprocess.Popen | None = None
        for s in (signal.SIGINT, signal.SIGTERM):
            signal.signal(s, self._handle)

    def _handle(self, signum, _frame) -> None:
        self.signum = signum
        if self.child is not None and self.child.poll() is None:
            self.child.send_signal(signum)


def train_cell(cell, run_dir: Path, stop: Stop, part=None) -> int:
    """Train (or resume) one cell (or one program of it, ``part``) with train.py; its output is
    shown and appended to ``<run_dir>/train.log``."""
    from mjx_collo import study as study_lib

    run_dir.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, str(ROOT / "train.py"), *study_lib.train_args(cell, run_dir, part)]
    tag = f"{cell.key} {part.name}" if part and part.name else cell.key
    with open(run_dir / "train.log", "a") as log:
        log.write(f"\n# {time.strftime('%Y-%m-%d %H:%M:%S')} {' '.join(cmd)}\n")
        log.flush()
        stop.child = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT
        )
        for line in stop.child.stdout:
            sys.stdout.write(f"[{tag}] {line}")
            sys.stdout.flush()
            log.write(line)
        code = stop.child.wait()
        stop.child = None
    return code


def main(argv: list[str] | None = None) -> int:
    args = parse(argv)
    import envs  # noqa: F401  (validates task names in study.load)
    from mjx_collo import report, study

    try:
        name, cfg = study.load(args.study)
    except study.StudyError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    root = Path(args.root) if args.root else Path("runs") / "study" / name
    results = Path(args.results) if args.results else ROOT / "results" / "study" / name
    out = Path(args.out) if args.out else ROOT / "docs" / "results" / f"{name}.md"
    cells = study.cells(cfg)
    if args.only:
        wanted = {x.strip() for x in args.only.split(",") if x.strip()}
        known = {c.variant.name for c in cells} | {c.task for c in cells}
        if wanted - known:
            print(
                f"error: --only {','.join(sorted(wanted - known))}: not a variant or task of "
                f"{name}; choose from {', '.join(sorted(known))}",
                file=sys.stderr,
            )
            return 2
        picked = [c for c in cells if c.variant.name in wanted or c.task in wanted]
        if wanted & {c.variant.name for c in cells} and wanted & {c.task for c in cells}:
            picked = [c for c in cells if c.variant.name in wanted and c.task in wanted]
        cells = picked

    if args.action == "status":
        for key, state in study.status(root, cfg, results).items():
            print(f"{key:<40s} {state}")
        return 0
    if args.action == "report":
        path = report.write(name, cfg, results, out)
        print(f"wrote {path}")
        return 0

    from mjx_collo import session

    try:
        added = study.pin_config(root, cfg)
        lock = session.lock_run_dir(root)  # noqa: F841 (one study process per root)
    except (study.StudyError, session.RunLocked) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    stop = Stop()
    failed: list[str] = []
    trained = 0
    print(f"study {name}: {len(cells)} cells x {cfg.seeds} seeds -> {root}")
    if added:
        print(f"study {name} grew since it started: {', '.join(added)} (cells trained so far kept)")
    for i, cell in enumerate(cells, 1):
        if study.is_finished(root, cell):
            study.collect(root, cell, results)
            print(f"[{i}/{len(cells)}] {cell.key}: finished, skipped")
            continue
        if study.recorded_finished(results, cell):
            rec = results / cell.task / cell.variant.name
            print(f"[{i}/{len(cells)}] {cell.key}: finished in the committed record {rec}, skipped")
            continue
        if args.max_cells is not None and trained >= args.max_cells:
            print(f"stopping after {trained} cell(s) (--max-cells)")
            break
        parts = study.parts(root, cell)
        if len(parts) > 1 and study.checkpoint_steps(study.cell_dir(root, cell)):
            print(
                f"[{i}/{len(cells)}] {cell.key}: trains in parts now (seeds_per_program); the "
                f"whole-cell checkpoints in {study.cell_dir(root, cell) / 'checkpoints'} are "
                "not resumed"
            )
        did_train = False
        for part in parts:
            where = f"{cell.key} {part.name}" if part.name else cell.key
            if len(parts) > 1:
                if study.part_finished(part, cell):
                    print(f"[{i}/{len(cells)}] {where}: finished, skipped")
                    continue
                if study.recorded_finished(results, cell, part.labels):
                    print(f"[{i}/{len(cells)}] {where}: finished in the committed record, skipped")
                    continue
                last = part.first + part.seeds - 1
                seeds = f"seed {last}" if part.seeds == 1 else f"seeds {part.first}-{last}"
                where += f" ({seeds} of {cell.seeds})"
            print(f"[{i}/{len(cells)}] {where}: training {cell.steps} env steps -> {part.dir}")
            code = train_cell(cell, part.dir, stop, part)
            did_train = True
            study.collect(root, cell, results)
            if stop.signum is not None:
                print(f"study {name} interrupted in {where}; the same command resumes it")
                return 128 + stop.signum
            if code != 0 or not study.part_finished(part, cell):
                failed.append(f"{where} (exit {code}, log {part.dir / 'train.log'})")
                break
        study.collect(root, cell, results)  # parts finished here but not yet in the record
        trained += did_train
    if not args.no_report:
        print(f"wrote {report.write(name, cfg, results, out)}")
    if failed:
        print("error: cells that did not finish: " + "; ".join(failed), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Combine the seeds of several run directories into one: ``make combine RUNS="a b c" OUT=dir``.

Seeds trained in separate runs (another day, another machine, ``run.seed=1`` after ``run.seed=0``)
become one ``metrics.jsonl`` with the seeds renumbered 0..N-1 in the order given, the same PNG
plots ``train.py`` draws (mean over seeds, min-max band), and ``summary.json`` with every
evaluation's per-seed returns and their mean. Runs whose resolved configs differ in anything but
``run.seed`` and ``run.steps`` are refused with the differing keys named (``--force`` combines
them anyway and records the differences).
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import yaml

from mjx_collo import config as config_lib
from mjx_collo import metrics as metrics_lib

# Keys that may differ between runs of one experiment: which seed, and how long it ran.
ALLOWED = ("run.seed", "run.steps")


def _read_run(run_dir: Path) -> tuple[list[dict], dict]:
    path = run_dir / "metrics.jsonl"
    if not path.exists():
        raise SystemExit(f"{run_dir}: no metrics.jsonl (is this a run directory of train.py?)")
    rows, _ = metrics_lib.read_rows(path)
    cfg_path = run_dir / "config.yaml"
    cfg = yaml.safe_load(cfg_path.read_text()) if cfg_path.exists() else {}
    # keys added since a run was written hold the value it ran with (config.ADDED_KEYS)
    return rows, config_lib.flatten(config_lib.complete_saved(cfg) if cfg else {})


def config_differences(configs: list[dict]) -> list[str]:
    """``key: value (run 0) vs value (run i)`` for every key outside ``ALLOWED`` that differs
    (keys inert in both runs, :func:`config.inert_keys`, do not count)."""
    out = []
    first = configs[0]
    for i, other in enumerate(configs[1:], start=1):
        inert = config_lib.inert_keys(first) & config_lib.inert_keys(other)
        for key in sorted((set(first) | set(other)) - inert):
            if key not in ALLOWED and first.get(key) != other.get(key):
                out.append(f"{key}: {first.get(key)!r} (run 0) vs {other.get(key)!r} (run {i})")
    return out


def combine(run_dirs: list[Path], out: Path, force: bool = False) -> dict:
    """Write ``out/metrics.jsonl``, ``out/plots/*.png`` and ``out/summary.json``; return the
    summary."""
    if not run_dirs:
        raise SystemExit("combine: give at least one run directory")
    read = [_read_run(Path(d)) for d in run_dirs]
    differences = config_differences([cfg for _, cfg in read])
    if differences and not force:
        raise SystemExit(
            "combine: these runs were trained with different configs, so their seeds are not one "
            "experiment:\n  " + "\n  ".join(differences) + "\nPass --force to combine them anyway."
        )
    rows, sources, offset = [], [], 0
    for d, (run_rows, cfg) in zip(run_dirs, read, strict=True):
        seeds = sorted({r["seed"] for r in run_rows})
        renumber = {s: offset + j for j, s in enumerate(seeds)}
        for r in run_rows:
            rows.append({**r, "seed": renumber[r["seed"]]})
        sources += [
            {"seed": renumber[s], "run": str(d), "index_in_run": s, "run.seed": cfg.get("run.seed")}
            for s in seeds
        ]
        offset += len(seeds)
    rows.sort(key=lambda r: (r["step"], r["kind"] != "train", r["seed"]))

    out = Path(out)
    if (out / "metrics.jsonl").exists():
        (out / "metrics.jsonl").unlink()  # RunLog would keep it as history
    log = metrics_lib.RunLog(out, total_steps=0, num_seeds=offset, progress=False)
    log.rows = rows
    log.file.write("".join(json.dumps(r) + "\n" for r in rows))
    log.plot()
    log.close()

    evals: dict[int, dict[int, float]] = defaultdict(dict)
    for r in rows:
        if r["kind"] == "eval" and "eval/return" in r:
            evals[r["step"]][r["seed"]] = r["eval/return"]
    summary = {
        "seeds": sources,
        "config_differences": differences,
        "eval_return": {
            str(step): {
                "per_seed": [round(by_seed[s], 1) for s in sorted(by_seed)],
                "mean": round(sum(by_seed.values()) / len(by_seed), 1),
                "seeds": len(by_seed),
            }
            for step, by_seed in sorted(evals.items())
        },
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    return summary


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="run directories, in seed order")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--force", action="store_true", help="combine runs whose configs differ")
    args = ap.parse_args(argv)
    summary = combine(args.runs, args.out, args.force)
    print(f"{len(summary['seeds'])} seed(s) -> {args.out}")
    for step, e in summary["eval_return"].items():
        per = ", ".join(f"{v:.1f}" for v in e["per_seed"])
        print(f"  eval at {step:>7}: mean {e['mean']:.1f} over {e['seeds']} ({per})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

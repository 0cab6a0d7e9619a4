"""Dump a run's world-model parameters and first replay rows to one ``.npz`` (benchmark fixtures).

Usage: ``python benchmarks/dump_model.py RUN_DIR OUT.npz --env cheetah --method cem [overrides]``
with the same method, seeds (1) and overrides the run was trained with; the run's latest
checkpoint is restored exactly as ``train.py`` resumes it. Keys: ``wm<keypath>`` per parameter
(seed axis dropped) and ``replay/<field>`` ([rows, envs, ...], the first ``--rows`` rows).
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

import envs
from mjx_collo import config, runner


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir")
    ap.add_argument("out")
    ap.add_argument("--env", default="cheetah")
    ap.add_argument("--method", default="cem")
    ap.add_argument("--preset", action="append", default=[])
    ap.add_argument("--rows", type=int, default=6000)
    ap.add_argument("overrides", nargs="*")
    args = ap.parse_intermixed_args(argv)
    cfg = config.load(
        task=envs.canonical(args.env),
        method=args.method,
        presets=args.preset,
        overrides=args.overrides,
    )
    run = runner.Run(cfg, envs.from_config(cfg.env), args.run_dir, num_seeds=1, progress=False)
    state, _ = run.start()
    arrays = {}
    for path, leaf in jax.tree_util.tree_flatten_with_path(state.wm)[0]:
        arrays["wm" + jax.tree_util.keystr(path)] = np.asarray(leaf)[0]
    rows = min(args.rows, int(np.asarray(state.replay.count).reshape(-1)[0]))
    for k, v in state.replay.data.items():
        arrays["replay/" + k] = np.asarray(v)[0, :rows]
    np.savez_compressed(args.out, **arrays)
    print(f"wrote {args.out}: {len(arrays)} arrays, {rows} replay rows")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

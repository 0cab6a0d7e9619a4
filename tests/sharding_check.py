"""Run by test_distributed.py in a subprocess with 2 forced host devices: one debug chunk with the
seed axis sharded over both devices vs the same chunk unsharded; prints a JSON comparison."""

from __future__ import annotations

import json
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np

import envs
from mjx_collo import config, parallel, trainer


def main() -> None:
    assert jax.device_count() == 2, f"expected 2 devices, got {jax.devices()}"
    cfg = config.load(task="reacher_easy", presets=["debug"])
    env = envs.from_config(cfg.env)
    tr = trainer.make_train(cfg, env)
    keys = parallel.seed_keys(cfg, 2)
    out = {}
    for name, sharding in (("unsharded", None), ("sharded", parallel.mesh_sharding(2))):
        init, chunk, _ = parallel.batched(tr, sharding)
        state = init(keys, {})
        state, metrics = chunk(state, jnp.int32(0))
        if sharding is not None:
            assert (
                len(state.wm_opt[0].mu.sharding.device_set) == 2
                if hasattr(state.wm_opt[0], "mu")
                else True
            )
        out[name] = jax.device_get((state, metrics))
    a, b = out["unsharded"], out["sharded"]
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    diffs = [
        float(np.max(np.abs(np.asarray(x, np.float64) - np.asarray(y, np.float64))))
        if np.asarray(x).size
        else 0.0
        for x, y in zip(la, lb, strict=True)
    ]
    # The state must be finite; metrics legitimately hold NaN where nothing happened (prefill
    # iterations have no plan metrics, most iterations end no episode).
    finite = [bool(np.all(np.isfinite(np.asarray(x, np.float64)))) for x in jax.tree.leaves(a[0])]
    print(
        json.dumps(
            {
                "max_abs_diff": max(diffs),
                "exact": all(d == 0 for d in diffs),
                "leaves": len(la),
                "all_finite": all(finite),
                "updates": np.asarray(a[0].updates).tolist(),
            }
        )
    )


if __name__ == "__main__":
    sys.path.insert(0, os.getcwd())
    main()

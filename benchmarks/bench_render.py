"""Render throughput: ms per 64x64 frame of ``envs.render`` at batch 1, 16 and 64, per task.

The renderer runs inside the env step when ``env.obs=pixels``; this times it alone, jitted and vmapped
over a batch of states from random rollouts (each env in its own pose), on one device. Target: <= 1 ms per
frame per env at batch 16 on 2 cores. Prints a table and writes ``bench_results/render.json``.

    make bench-render
    make bench-render ARGS="--tasks cheetah_run --batches 16 --size 64"
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import time
from pathlib import Path


def parse() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--tasks", nargs="*", default=None, help="default: every registered task")
    p.add_argument("--batches", nargs="*", type=int, default=[1, 16, 64])
    p.add_argument("--size", type=int, default=64)
    p.add_argument("--calls", type=int, default=20, help="renders per timed repeat")
    p.add_argument("--repeats", type=int, default=5, help="timed repeats (best is reported)")
    p.add_argument("--out", default="bench_results/render.json")
    return p.parse_args()


def measure(task: str, batches, size: int, calls: int, repeats: int) -> dict:
    import jax

    import envs
    from envs import render

    env = envs.make(task, normalize_actions=True)
    bare = env.unwrapped
    scene = render.make_scene(bare.mj_model, size, size, render.camera_for(bare))
    row = {
        "task": task,
        "size": size,
        "geoms_drawn": int(sum(len(v) for v in scene.geoms.values())),
    }
    for b in batches:

        @functools.partial(jax.jit, static_argnums=1)
        def states(key, b):
            def one(k):
                k_reset, k_act = jax.random.split(k)
                acts = jax.random.uniform(k_act, (20, env.action_size), minval=-1, maxval=1)
                s, _ = jax.lax.scan(lambda s, a: (env.step(s, a), None), env.reset(k_reset), acts)
                return s

            return jax.vmap(one)(jax.random.split(key, b))

        s = states(jax.random.PRNGKey(0), b)
        data = s.pipeline_state
        frames = jax.jit(jax.vmap(lambda d: render.render_data(scene, d)))
        t0 = time.perf_counter()
        frames(data).block_until_ready()
        compile_s = time.perf_counter() - t0
        best = float("inf")
        for _ in range(repeats):
            t0 = time.perf_counter()
            for _ in range(calls):
                out = frames(data)
            out.block_until_ready()
            best = min(best, (time.perf_counter() - t0) / calls)
        row[f"batch{b}"] = {
            "ms_per_call": 1e3 * best,
            "ms_per_frame": 1e3 * best / b,
            "compile_s": compile_s,
        }
        print(
            f"{task:16s} batch {b:3d}: {1e3 * best / b:7.3f} ms/frame ({1e3 * best:8.2f} ms/call), "
            f"compile {compile_s:5.1f}s",
            flush=True,
        )
    return row


def main() -> None:
    args = parse()
    import envs

    tasks = args.tasks or envs.registered()
    unknown = sorted(set(tasks) - set(envs.registered()))
    if unknown:
        raise SystemExit(f"unknown task(s) {unknown}; registered: {envs.registered()}")
    rows = [measure(t, args.batches, args.size, args.calls, args.repeats) for t in tasks]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    result = {
        "host": {
            "machine": platform.machine(),
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
        },
        "target_ms_per_frame_batch16": 1.0,
        "rows": rows,
    }
    out.write_text(json.dumps(result, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

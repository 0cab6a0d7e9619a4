"""Env throughput: batched MJX vs native MuJoCo on the same model, plus compile time per task.

Prints a table and writes ``bench_results/envs.json``. Control steps/s (one dm_control control step =
``n_substeps`` physics steps) for our MJX env at batch 1, 16, 64, 256 (one device, and the batch
sharded over two CPU devices = both cores), and native ``mujoco.rollout`` on the same compiled model
with 1 and 2 threads. Target: batched MJX >= 0.5x native single-thread throughput, compile <= 30 s.

    make bench-envs                      # all tasks
    make bench-envs ARGS="--tasks cheetah_run --batches 64"

Each task is measured in a fresh process (compile times are a first launch's). A run with ``--tasks``
replaces those tasks' rows in an existing JSON and keeps the others; the file is rewritten after each
task, so a long run that is interrupted keeps the tasks it finished.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path


def parse() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--tasks", nargs="*", default=None, help="default: every registered task")
    p.add_argument("--batches", nargs="*", type=int, default=[1, 16, 64, 256])
    p.add_argument("--steps", type=int, default=200, help="control steps per timed rollout")
    p.add_argument("--repeats", type=int, default=3, help="timed repeats (best is reported)")
    p.add_argument("--out", default="bench_results/envs.json")
    return p.parse_args()


def main() -> None:
    args = parse()
    # Two host devices so the batch can be sharded over both cores (set before jax starts).
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_force_host_platform_device_count" not in flags:
        os.environ["XLA_FLAGS"] = (flags + " --xla_force_host_platform_device_count=2").strip()
    import envs

    tasks = args.tasks or envs.registered()
    unknown = sorted(set(tasks) - set(envs.registered()))
    if unknown:
        raise SystemExit(f"unknown task(s) {unknown}; registered: {envs.registered()}")
    if len(tasks) > 1:
        # One fresh process per task: trace and compile times are those of a first launch, not
        # of a process whose heap and caches hold the previous tasks (that added up to 5 s).
        for task in tasks:
            cmd = [sys.executable, __file__, "--tasks", task, "--out", args.out]
            cmd += ["--steps", str(args.steps), "--repeats", str(args.repeats), "--batches"]
            subprocess.run(cmd + [str(b) for b in args.batches], check=True)
    else:
        measure(args, tasks[0])
    summary(args.out)


def measure(args: argparse.Namespace, task: str) -> None:
    """Measure one task and update its row in ``args.out``."""
    import jax
    import jax.numpy as jnp
    import mujoco
    import numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec
    from mujoco import rollout

    import envs

    devices = jax.devices()
    mesh = Mesh(np.array(devices[:2]), ("batch",))
    out = Path(args.out)
    # A partial run (--tasks ...) updates its tasks in an existing file and keeps the others, so
    # the suite can be measured task by task; the file is rewritten after every task.
    old = json.loads(out.read_text()) if out.exists() else {}
    results = {
        "machine": {"cpu_count": os.cpu_count(), "platform": platform.platform()},
        "jax": jax.__version__,
        "mujoco": mujoco.__version__,
        "steps": args.steps,
        "tasks": old.get("tasks", {}) if old.get("steps") == args.steps else {},
    }

    def best_time(fn, *a):
        times = []
        for _ in range(args.repeats):
            t = time.perf_counter()
            jax.block_until_ready(fn(*a))
            times.append(time.perf_counter() - t)
        return min(times)

    def make_rollout(env, batch: int, steps: int):
        low, high = jnp.asarray(env.action_low), jnp.asarray(env.action_high)

        def run(state, key):
            def body(s, k):
                a = jax.random.uniform(k, (batch, env.action_size), minval=low, maxval=high)
                return jax.vmap(env.step)(s, a), None

            state, _ = jax.lax.scan(body, state, jax.random.split(key, steps))
            return state.obs

        return run

    env = envs.make(task)
    n_sub = env.n_substeps
    row: dict = {"n_substeps": n_sub, "mjx": {}, "mjx_2dev": {}, "native": {}}

    key = jax.random.PRNGKey(0)
    for batch in args.batches:
        states = jax.jit(jax.vmap(env.reset))(jax.random.split(key, batch))
        run = jax.jit(make_rollout(env, batch, args.steps))
        t = time.perf_counter()
        lowered = run.lower(states, key)
        t_trace = time.perf_counter() - t
        compiled = lowered.compile()
        t_compile = time.perf_counter() - t - t_trace
        compiled(states, key).block_until_ready()
        dt = best_time(compiled, states, key)
        row["mjx"][batch] = batch * args.steps / dt
        if batch == args.batches[0]:
            row["trace_s"], row["compile_s"] = t_trace, t_compile
        if batch >= 2 and batch % 2 == 0:
            sh = NamedSharding(mesh, PartitionSpec("batch"))
            states2 = jax.device_put(states, sh)
            run2 = jax.jit(
                make_rollout(env, batch, args.steps), in_shardings=(sh, None), out_shardings=sh
            )
            run2(states2, key).block_until_ready()
            row["mjx_2dev"][batch] = batch * args.steps / best_time(run2, states2, key)
        print(
            f"{task:15s} batch {batch:4d}: MJX {row['mjx'][batch]:9.0f} ctrl steps/s"
            + (f", 2 devices {row['mjx_2dev'][batch]:9.0f}" if batch in row["mjx_2dev"] else ""),
            flush=True,
        )

    # Native MuJoCo on the same (tuned) compiled model, float64, no Python in the loop.
    m = env.mj_model
    size = mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_FULLPHYSICS)
    rng = np.random.default_rng(0)
    for threads in (1, 2):
        batch = max(args.batches)
        s0 = jax.device_get(jax.jit(jax.vmap(env.reset))(jax.random.split(key, batch)))
        init = np.zeros((batch, size))
        for i in range(batch):
            d = mujoco.MjData(m)
            d.qpos[:] = s0.pipeline_state.qpos[i]
            d.qvel[:] = s0.pipeline_state.qvel[i]
            mujoco.mj_getState(m, d, init[i], mujoco.mjtState.mjSTATE_FULLPHYSICS)
        ctrl = rng.uniform(env.action_low, env.action_high, (batch, args.steps, m.nu))
        ctrl = np.repeat(ctrl, n_sub, axis=1)
        datas = [mujoco.MjData(m) for _ in range(threads)]
        with rollout.Rollout(nthread=threads) as r:
            r.rollout(m, datas, init, ctrl, nstep=args.steps * n_sub)
            times = []
            for _ in range(args.repeats):
                t = time.perf_counter()
                r.rollout(m, datas, init, ctrl, nstep=args.steps * n_sub)
                times.append(time.perf_counter() - t)
        row["native"][threads] = batch * args.steps / min(times)
    best_mjx = max(list(row["mjx"].values()) + list(row["mjx_2dev"].values()))
    row["best_mjx_over_native_1thread"] = best_mjx / row["native"][1]
    row["target_0.5x_met"] = row["best_mjx_over_native_1thread"] >= 0.5
    row["compile_target_30s_met"] = row["trace_s"] + row["compile_s"] <= 30
    print(
        f"{task:15s} native 1 thread {row['native'][1]:9.0f}, 2 threads "
        f"{row['native'][2]:9.0f} ctrl steps/s | best MJX / native-1 = "
        f"{row['best_mjx_over_native_1thread']:.2f} | trace {row['trace_s']:.1f}s + "
        f"compile {row['compile_s']:.1f}s",
        flush=True,
    )
    results["tasks"][task] = row
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=2))


def summary(path: str) -> None:
    results = json.loads(Path(path).read_text())
    print(f"\n{'task':15s} {'MJX best':>10s} {'native x1':>10s} {'ratio':>6s} {'compile s':>9s}")
    for task, row in results["tasks"].items():
        best = max(list(row["mjx"].values()) + list(row["mjx_2dev"].values()))
        print(
            f"{task:15s} {best:10.0f} {row['native']['1']:10.0f} "
            f"{row['best_mjx_over_native_1thread']:6.2f} {row['trace_s'] + row['compile_s']:9.1f}"
        )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

"""Whole-loop training throughput: env steps/s, wall time per seed count, launch -> first update.

Usage: ``python benchmarks/bench_train.py [--task cheetah] [--methods collodreamer,latco,dreamer]
[--seeds 1,2,4] [--out bench_results/train.json]``. Prints a table and writes JSON.

Every measurement runs ``mjx_collo.runner.Run`` (what ``make train`` runs) with the default config
of the method in a fresh process with an empty XLA cache, so compile times are those of a first
launch. Each process runs the prefill chunks and one steady-state chunk; to keep the benchmark
short the chunk is 1000 env steps (one training call of ``run.train_steps`` updates plus 500
acting steps) instead of the default 5000, which changes only how often the host logs. From the
measured chunks the time of a whole run is

    compile + init + prefill chunks + (steps - prefill) / 1000 x steady chunk + evaluations,

with the evaluation time measured once per method and seed count (after its compile). A single
run evaluates on a second CPU device beside the next chunks (``run.eval_overlap``): the worker
also times such a window (an evaluation started, steady chunks until it is done), and each
evaluation but the last then costs the window less its chunks alone. Seed counts
run as ``make train SEEDS=n`` does: on the CPU devices ``mjx_collo.host_devices`` gives n seeds, unless
``XLA_FLAGS`` sets the device count. Launch -> first update is
measured from process start (imports included) to the end of the chunk holding the first update,
cold (empty cache) and warm (a second launch with the cache the first one filled).
"""

from __future__ import annotations

import time

_T0 = time.perf_counter()

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import platform  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
STEADY_CHUNK = 1000


def worker(spec: dict) -> dict:
    """Runs in a child process: prefill + ``spec['steady']`` steady chunks of one config."""
    sys.path.insert(0, str(ROOT))
    from mjx_collo import host_devices

    host_devices.configure(spec["seeds"])  # as train.py does, before JAX starts
    import jax

    jax.config.update("jax_compilation_cache_dir", spec["cache"])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    import envs
    from mjx_collo import config, runner

    task = envs.canonical(spec["task"])
    overrides = [
        f"run.chunk_env_steps={STEADY_CHUNK}",
        f"run.steps={spec['total']}",
        *spec.get("overrides", []),
    ]
    cfg = config.load(task=task, method=spec["method"], overrides=overrides)
    env = envs.from_config(cfg.env)
    logs: list[str] = []
    r = runner.Run(cfg, env, spec["run"], num_seeds=spec["seeds"], progress=False, log=logs.append)
    prefill_chunks = -(-cfg.run.prefill // STEADY_CHUNK)
    start = time.perf_counter() - _T0
    res = r.run(max_chunks=prefill_chunks + spec["steady"])
    out = {
        "imports_and_build_s": start,
        "init_s": res.init_s,
        "compile_s": res.compile_s,
        "chunk_s": res.chunk_s,
        "prefill_chunks": prefill_chunks,
        "launch_to_first_update_s": start + res.first_update_s if res.first_update_s else None,
        "train_every": cfg.run.train_every,
        "train_steps": cfg.run.train_steps,
        "prefill": cfg.run.prefill,
        "eval_every": cfg.run.eval_every,
        "eval_episodes": cfg.run.eval_episodes,
        "devices": jax.device_count(),
        "matmul_budget": r.budget,  # GFLOP by schedule for a spec['total'] run (one seed)
        "log": logs,
    }
    if spec.get("eval"):
        t = time.perf_counter()
        r.evaluate(r.state, 0)
        out["eval_first_s"] = time.perf_counter() - t  # includes the eval program's compile
        t = time.perf_counter()
        r.evaluate(r.state, 1)
        out["eval_s"] = time.perf_counter() - t
        if r.eval_device is not None:  # run.eval_overlap: the evaluation beside training chunks
            out.update(overlap_window(r))
    r.close()
    from mjx_collo.flops import matmul_peak

    out["matmul_gflops"] = matmul_peak()  # the machine's speed, to compare timings across VMs
    b = out["matmul_budget"]
    # the fastest this run could be on this machine: its matmuls alone, at the matmul peak
    out["matmul_floor_run_s"] = b["run_gflop"] / out["matmul_gflops"]
    steady = out["chunk_s"][prefill_chunks:]
    steady_gflop = b["chunk_gflop"] * STEADY_CHUNK / cfg.run.chunk_env_steps
    out["steady_fraction_of_peak"] = (
        steady_gflop / (sum(steady) / len(steady)) / out["matmul_gflops"]
    )
    return out


def overlap_window(r) -> dict:
    """Start an evaluation on its own device and keep training steady chunks until it is done,
    as ``make train`` does after each evaluation point. Returns the window's wall time and how
    many chunks ran in it; the evaluation's cost in a run is the window less those chunks alone."""
    from mjx_collo import runner

    state, it = r.state, r.iteration
    t = time.perf_counter()
    future = r.start_evaluation(state, 2)
    chunks = 0
    while chunks == 0 or not future.done():
        state, stacked = r.chunk_program(state, r._it(it))
        runner.host(stacked)
        it += r.trainer.iterations_per_chunk
        chunks += 1
    overlapped_eval_s = future.result().seconds
    return {
        "overlap_window_s": time.perf_counter() - t,
        "overlap_chunks": chunks,
        "overlapped_eval_s": overlapped_eval_s,
    }


def launch(spec: dict) -> dict:
    """Run :func:`worker` in a fresh interpreter (fresh JAX, measured from process start)."""
    cmd = [sys.executable, __file__, "--worker", json.dumps(spec)]
    p = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    if p.returncode != 0:
        raise RuntimeError(f"worker {spec['method']} x{spec['seeds']} failed:\n{p.stderr[-3000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def steady_chunk_s(m: dict) -> float:
    """Mean wall seconds of the measured steady chunks (after prefill)."""
    steady = m["chunk_s"][m["prefill_chunks"] :]
    return sum(steady) / len(steady)


def overlap_extra_s(m: dict) -> float | None:
    """What one evaluation beside training adds to the run: its window less the chunks alone
    (None when the run evaluates in line)."""
    if "overlap_window_s" not in m:
        return None
    return max(0.0, m["overlap_window_s"] - m["overlap_chunks"] * steady_chunk_s(m))


def estimate(m: dict, steps: int, eval_s: float) -> float:
    """Wall seconds of a whole ``steps`` run from the measured pieces (see module doc). With
    ``run.eval_overlap`` every evaluation but the last runs beside the next chunks and costs
    what its window took beyond those chunks alone; the last one has nothing to overlap."""
    prefill = sum(m["chunk_s"][: m["prefill_chunks"]])
    per_chunk = steady_chunk_s(m)
    n_steady = max(0, steps - m["prefill_chunks"] * STEADY_CHUNK) / STEADY_CHUNK
    n_eval = steps // m["eval_every"]
    evals = n_eval * eval_s
    extra = overlap_extra_s(m)
    if extra is not None and n_eval:
        evals = (n_eval - 1) * min(extra, eval_s) + eval_s
    return (
        m["imports_and_build_s"]
        + m["init_s"]
        + m["compile_s"]
        + prefill
        + n_steady * per_chunk
        + evals
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--task", default="cheetah")
    ap.add_argument("--methods", default="collodreamer,latco,dreamer")
    ap.add_argument("--seeds", default="1,2,4", help="vmapped seed counts (default method)")
    ap.add_argument("--steps", type=int, default=100_000, help="run length the estimate is for")
    ap.add_argument("--out", default="bench_results/train.json")
    ap.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="config overrides for every measured run (e.g. planner.iters=1 to time the rest)",
    )
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(worker(json.loads(args.worker))))
        return

    from mjx_collo import host_devices  # imports nothing from JAX

    # Read before the first worker: afterwards the average counts the benchmark's own threads.
    load = os.getloadavg()[0]
    methods = args.methods.split(",")
    seed_counts = [int(s) for s in args.seeds.split(",")]
    tmp = Path(tempfile.mkdtemp(prefix="bench_train_"))
    rows, seeds_rows = [], []

    def spec(method: str, seeds: int, name: str, cache: str, ev: bool) -> dict:
        return {
            "task": args.task,
            "method": method,
            "seeds": seeds,
            "steady": 1,
            "total": args.steps,
            "cache": cache,
            "run": str(tmp / name),
            "eval": ev,
            "overrides": args.set,
        }

    for method in methods:
        print(f"... {method} x1 (cold cache)", flush=True)
        m = launch(spec(method, 1, f"{method}-1", str(tmp / f"cache-{method}"), True))
        m["method"], m["seeds"] = method, 1
        m["env_steps_per_s"] = STEADY_CHUNK / steady_chunk_s(m)
        m["estimated_run_s"] = estimate(m, args.steps, m["eval_s"])
        rows.append(m)
        print(
            f"    compile {m['compile_s']:.0f}s, steady {m['env_steps_per_s']:.1f} env steps/s, "
            f"first update {m['launch_to_first_update_s']:.0f}s, "
            f"{args.steps // 1000}k steps ~ {m['estimated_run_s'] / 60:.0f} min",
            flush=True,
        )
    base = rows[0]
    print(f"... {base['method']} x1 again (warm cache: launch -> first update)", flush=True)
    warm = launch(spec(base["method"], 1, "warm", str(tmp / f"cache-{base['method']}"), False))
    base["launch_to_first_update_warm_s"] = warm["launch_to_first_update_s"]
    base["compile_warm_s"] = warm["compile_s"]

    for n in seed_counts:
        if n == 1:
            m = base
        else:
            print(f"... {base['method']} x{n} seeds", flush=True)
            m = launch(spec(base["method"], n, f"seeds-{n}", str(tmp / f"cache-s{n}"), True))
        steady = steady_chunk_s(m)
        seeds_rows.append(
            {
                "seeds": n,
                "steady_chunk_s": steady,
                "compile_s": m["compile_s"],
                "devices": m["devices"],
                "env_steps_per_s_per_seed": STEADY_CHUNK / steady,
                "eval_s": m["eval_s"],
                "estimated_run_s": estimate(m, args.steps, m["eval_s"]),
            }
        )

    print(f"\n{args.task}, {args.steps} env steps, default config per method (cold compile)")
    print(
        f"{'method':14s} {'compile':>8s} {'env st/s':>9s} {'1st upd':>8s} {'eval':>6s} "
        f"{'est. run':>9s}"
    )
    for m in rows:
        print(
            f"{m['method']:14s} {m['compile_s']:7.0f}s {m['env_steps_per_s']:9.1f} "
            f"{m['launch_to_first_update_s']:7.0f}s {m['eval_s']:5.0f}s "
            f"{m['estimated_run_s'] / 60:7.1f}min"
        )
    for m in rows:
        if "overlap_window_s" in m:
            m["overlap_extra_s"] = overlap_extra_s(m)
            print(
                f"{m['method']:14s} evaluation beside training (run.eval_overlap): "
                f"{m['overlap_window_s']:.0f}s for it and {m['overlap_chunks']} chunks -> "
                f"+{m['overlap_extra_s']:.0f}s per evaluation (alone {m['eval_s']:.0f}s)"
            )
    print(
        f"\nmatmul work of one {args.steps}-step run (loops counted per iteration) and the least "
        f"time it needs at this machine's matmul peak ({base['matmul_gflops']:.0f} GFLOP/s)"
    )
    for m in rows:
        b = m["matmul_budget"]
        print(
            f"{m['method']:14s} {b['run_gflop'] / 1e3:7.0f} TFLOP ({100 * b['run_planning_share']:.0f}% "
            f"planning; call {b['plan_call_gflop_per_env']:.1f} GFLOP, update "
            f"{b['update_gflop']:.1f} GFLOP) -> >= {m['matmul_floor_run_s'] / 60:.0f} min; the "
            f"steady chunk ran at {100 * m['steady_fraction_of_peak']:.0f}% of the peak"
        )
    print(
        f"launch -> first update, warm cache: {base['launch_to_first_update_warm_s']:.0f}s "
        f"(chunk compile {base['compile_warm_s']:.1f}s)"
    )
    print(
        f"\n{'seeds':>5s} {'devices':>8s} {'steady chunk':>13s} {'eval':>6s} {'est. run':>9s} "
        f"{'x of 1 seed':>12s}"
    )
    one = seeds_rows[0]["estimated_run_s"]
    for s in seeds_rows:
        s["ratio_to_one_seed"] = s["estimated_run_s"] / one
        print(
            f"{s['seeds']:5d} {s['devices']:8d} {s['steady_chunk_s']:12.1f}s {s['eval_s']:5.0f}s "
            f"{s['estimated_run_s'] / 60:7.1f}min "
            f"{s['ratio_to_one_seed']:11.2f}x"
        )
    targets = {
        "run_100k_le_60min": base["estimated_run_s"] <= 3600 if args.steps == 100_000 else None,
        # False: even at the matmul peak the default's matmuls take longer than 60 min here
        "run_100k_matmul_floor_le_60min": (
            base["matmul_floor_run_s"] <= 3600 if args.steps == 100_000 else None
        ),
        "four_seeds_le_3x": next(
            (s["ratio_to_one_seed"] <= 3.0 for s in seeds_rows if s["seeds"] == 4), None
        ),
        "first_update_le_90s_cold": base["launch_to_first_update_s"] <= 90,
        "first_update_le_90s_warm": base["launch_to_first_update_warm_s"] <= 90,
    }
    verdict = {True: "met", False: "NOT met", None: "not measured"}
    print("targets:", ", ".join(f"{k}: {verdict[v]}" for k, v in targets.items()))
    if load > 1.0:
        print(f"warning: load average {load:.1f} before the benchmark: timings may be contended")
    result = {
        "task": args.task,
        "steps": args.steps,
        "steady_chunk_env_steps": STEADY_CHUNK,
        "methods": [{k: v for k, v in m.items() if k != "log"} for m in rows],
        "seeds": seeds_rows,
        "targets": targets,
        "machine": {
            "cpus": os.cpu_count(),
            "cpu": host_devices.cpu_model(),
            "platform": platform.platform(),
            "load_average_1min_before": load,
            "matmul_gflops": base["matmul_gflops"],
        },
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    from mjx_collo import xla_log_filter

    xla_log_filter.install()  # the workers inherit the filtered stderr
    main()

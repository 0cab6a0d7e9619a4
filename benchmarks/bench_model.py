"""World-model update throughput on CPU: updates/s, samples/s, achieved GFLOP/s vs matmul peak.

Usage: ``python benchmarks/bench_model.py [--seconds S] [--out bench_results/model.json]
[--only gaussian|categorical] [--batches 16x50,50x50]``. Prints a table and writes JSON.

Throughput figures use the best (minimum) update time and the best matmul time, sampled
alternately in the same window, so both see the same load on a shared machine; medians are in
the JSON too. FLOPs come from XLA's cost analysis. XLA counts a while-loop body once, not once per trip, so the
FLOPs of the compiled (scanned) update undercount the recurrent part; the benchmark therefore reads
them from the same update lowered with the time scan fully unrolled (``unroll=True``; lowered only,
never compiled or run), and reports both figures.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from mjx_collo import config
from mjx_collo import world_model as wm

OBS_DIM, ACT_DIM = 17, 6  # cheetah-run state observations and actions


def _flops(stage) -> float:
    ca = stage.cost_analysis()
    ca = ca[0] if isinstance(ca, list) else ca
    return float(ca.get("flops", 0.0))


class MatmulPeak:
    """Float32 matmul throughput of one large ``jnp.dot`` (``n x n x n``), best of repeats.

    ``sample()`` is called between update timings, so the peak is measured under the same
    (shared-machine) conditions as the updates it is compared with.
    """

    def __init__(self, n: int = 2048):
        self.n = n
        a = jax.random.normal(jax.random.key(0), (n, n), jnp.float32)
        b = jax.random.normal(jax.random.key(1), (n, n), jnp.float32)
        self.args = (a, b)
        self.f = jax.jit(jnp.dot).lower(a, b).compile()
        self.best = float("inf")
        self.sample()

    def sample(self) -> None:
        t = time.perf_counter()
        self.f(*self.args).block_until_ready()
        self.best = min(self.best, time.perf_counter() - t)

    @property
    def gflops(self) -> float:
        return 2 * self.n**3 / self.best / 1e9


def _batch(key: jax.Array, b: int, t: int) -> dict[str, jax.Array]:
    k1, k2, k3 = jax.random.split(key, 3)
    return {
        "obs": jax.random.normal(k1, (b, t, OBS_DIM)),
        "action": jax.random.uniform(k2, (b, t, ACT_DIM), minval=-1, maxval=1),
        "reward": jax.random.uniform(k3, (b, t)),
        "is_first": jnp.zeros((b, t), bool).at[:, 0].set(True),
    }


def bench_update(
    cfg: config.WorldModelConfig, b: int, t: int, seconds: float, peak: MatmulPeak
) -> dict:
    """Compile and time ``train_step`` at batch ``b x t`` (interleaved with peak samples)."""
    params = wm.init(cfg, jax.random.key(0), (OBS_DIM,), ACT_DIM)
    opt = wm.init_opt_state(cfg, params)
    batch = _batch(jax.random.key(1), b, t)
    key = jax.random.key(2)
    step = jax.jit(functools.partial(wm.train_step, cfg), donate_argnums=(0, 1))

    t0 = time.perf_counter()
    lowered = step.lower(params, opt, batch, key)
    compiled = lowered.compile()
    compile_s = time.perf_counter() - t0
    flops_compiled = _flops(compiled)
    unrolled = jax.jit(functools.partial(wm.train_step, cfg, unroll=True))
    flops = _flops(unrolled.lower(params, opt, batch, key))

    params, opt, m, _ = compiled(params, opt, batch, key)  # warm-up
    jax.block_until_ready(params)
    times, t_end = [], time.perf_counter() + seconds
    while time.perf_counter() < t_end or len(times) < 3:
        t1 = time.perf_counter()
        params, opt, m, _ = compiled(params, opt, batch, key)
        jax.block_until_ready(params)
        times.append(time.perf_counter() - t1)
        peak.sample()
    times.sort()
    best, median = times[0], times[len(times) // 2]
    return {
        "latent": cfg.latent,
        "batch": b,
        "length": t,
        "compile_s": compile_s,
        "update_ms_best": 1e3 * best,
        "update_ms_median": 1e3 * median,
        "updates_per_s": 1.0 / best,
        "samples_per_s": b * t / best,
        "updates_per_s_median": 1.0 / median,
        "gflop_per_update": flops / 1e9,
        "gflop_per_update_xla_compiled": flops_compiled / 1e9,
        "gflops_achieved": flops / best / 1e9,
        "gflops_achieved_median": flops / median / 1e9,
        "n_timed": len(times),
        "params": int(sum(x.size for x in jax.tree.leaves(params))),
        "finite": bool(m["nonfinite"] == 0),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=6.0, help="timing window per configuration")
    ap.add_argument("--out", default="bench_results/model.json")
    ap.add_argument("--only", choices=["gaussian", "categorical"], default=None)
    ap.add_argument("--batches", default="8x50,16x50,50x50")  # 8 x 50: the default since 2026-12-07
    args = ap.parse_args()

    peak = MatmulPeak()
    default = config.load()
    cfgs = {
        "categorical": default.wm,  # defaults: DreamerV2 32x32, deter 200
        "gaussian": config.load(method="latco").wm,  # D1/LC: stoch 30, plain GRU
    }
    batches = [tuple(int(x) for x in s.split("x")) for s in args.batches.split(",")]
    rows = []
    for name, cfg in cfgs.items():
        if args.only and name != args.only:
            continue
        for b, t in batches:
            print(f"... {name} {b}x{t}", flush=True)
            r = bench_update(cfg, b, t, args.seconds, peak)
            r["default_batch"] = (b, t) == (default.replay.batch, default.replay.length)
            rows.append(r)
    # Fractions use the best matmul time of the whole run (the most conservative peak).
    print(f"\nfloat32 matmul peak (2048^3 jnp.dot, best of run): {peak.gflops:.1f} GFLOP/s")
    header = (
        f"{'latent':12s} {'batch':>6s} {'compile':>8s} {'ms/upd':>8s} {'upd/s':>6s} "
        f"{'samples/s':>9s} {'GFLOP/upd':>9s} {'GFLOP/s':>8s} {'% peak':>7s}"
    )
    print(header)
    for r in rows:
        r["fraction_of_peak"] = r["gflops_achieved"] / peak.gflops
        mark = "  <- default batch" if r["default_batch"] else ""
        print(
            f"{r['latent']:12s} {r['batch']:>3d}x{r['length']:<2d} {r['compile_s']:7.1f}s "
            f"{r['update_ms_best']:8.1f} {r['updates_per_s']:6.2f} {r['samples_per_s']:9.0f} "
            f"{r['gflop_per_update']:9.2f} {r['gflops_achieved']:8.1f} "
            f"{100 * r['fraction_of_peak']:6.1f}%{mark}"
        )
    ok = all(r["fraction_of_peak"] >= 0.30 for r in rows if r["default_batch"])
    print(f"target >= 30% of peak at the default batch: {'met' if ok else 'NOT met'}")
    load = os.getloadavg()[0]
    if load > (os.cpu_count() or 1):
        print(f"warning: load average {load:.1f} on {os.cpu_count()} CPUs: timings are contended")
    result = {
        "matmul_peak_gflops": peak.gflops,
        "target_fraction_of_peak": 0.30,
        "rows": rows,
        "machine": {
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
            "jax": jax.__version__,
            "xla_flags": os.environ.get("XLA_FLAGS", ""),
            "load_average_1min": load,
        },
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

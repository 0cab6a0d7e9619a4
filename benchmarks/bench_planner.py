"""Planner benchmark: cost per planning call and return per CPU second (``make bench-planner``).

Model: the real world model's plan-space adapter (``world_model.latent_model``, as the trainer builds it) with random weights
at the default sizes (categorical 32x32 RSSM, deter 200, reward MLP 2x400; ``reduced`` space unless
noted), a random-weight value net (3x400) for the bootstrapping planners, action dim 6 (cheetah).
Contexts are model states after 10 random-action steps from the zero state.

Sections:
  calls   ms per planning call per env at H=30 (cold start, batch 1 and 16 envs, vmapped), compile
          time, matmul GFLOP per call (``mjx_collo.flops``: every loop counted per iteration),
          achieved GFLOP/s, iterations to the violation threshold, final violation, shadow return.
          Configurations whose full call would run for minutes (exact Gauss-Newton, CEM/MPPI with
          1000 samples at 16 envs) are timed on fewer iterations and extrapolated linearly in K;
          the table marks them ``extrap``.
  mpc     return per CPU second: 16 envs run 4 replanning rounds of 15 steps *inside the model*
          (execute the plan's actions with the model's mean transition, re-plan from the reached
          state, warm start as configured) for several solver / iteration settings; reports the
          executed model return, its gain over random actions (paired: same starts and keys), and
          GFLOP and ms per planning call. Random weights do not rank planners the way a trained
          model does (30 warm Adam steps won here and did not plan at all on a trained model):
          the defaults are chosen with ``bench_plan_quality.py`` instead. It uses the LatCo
          preset's model (Gaussian RSSM, stoch 30; 2.7x cheaper than the categorical one) and the
          reward-only objective: a random-weight value is not a correct value, and chasing it would
          not show in the executed reward. Exact Gauss-Newton is left out (a minute per call).

Writes ``bench_results/planner.json`` (rows of a partial rerun replace their old rows). Timings are
wall-clock on a shared CPU; GFLOP counts are deterministic. A full run takes ~20 min on 2 cores
(exact Gauss-Newton and 1000-sample CEM/MPPI dominate); run parts with e.g.
``make bench-planner ARGS="--section calls --only collodreamer/adam --batches 16"``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from mjx_collo import agent as agent_lib
from mjx_collo import config
from mjx_collo import value as value_lib
from mjx_collo import world_model as wm
from mjx_collo.config import Config
from mjx_collo.flops import matmul_flops, matmul_peak
from mjx_collo.planner import (
    COLLOCATION,
    LatentModel,
    cache_len,
    make_planner,
    mpc_init,
    next_action,
    replan,
)
from mjx_collo.planners import collocation, shooting
from mjx_collo.planners.objective import make_problem

ACTION_DIM = 6
OBS_DIM = 17
ROOT = Path(__file__).resolve().parent.parent


# ------------------------------------------------------------------------------------------------
# Model
# ------------------------------------------------------------------------------------------------


def build(cfg: Config, key: jax.Array) -> tuple[LatentModel, Any]:
    """(protocol model, params) for ``cfg``; params = (wm, target value) when bootstrapping."""
    k_wm, k_v = jax.random.split(key)
    wparams = wm.init(cfg.wm, k_wm, (OBS_DIM,), ACTION_DIM)
    vstate = value_lib.init_value(cfg.value, k_v, wm.feat_size(cfg.wm))
    model = agent_lib.make_agent(cfg, ACTION_DIM).model  # the trainer's model
    return model, (wparams, vstate.target)


def contexts(cfg: Config, params: Any, key: jax.Array, n: int) -> wm.RSSMState:
    """n posterior-like states: 10 random-action mean steps from the zero state. -> [n, ...]"""

    def one(k: jax.Array) -> wm.RSSMState:
        acts = jax.random.uniform(k, (10, ACTION_DIM), minval=-1.0, maxval=1.0)
        step = lambda s, a: (wm.img_step_mean(cfg.wm, params[0], s, a), None)
        return jax.lax.scan(step, wm.initial_state(cfg.wm), acts)[0]

    return jax.vmap(one)(jax.random.split(key, n))


def load(method: str, overrides: list[str]) -> Config:
    return config.load(method=method, overrides=overrides)


# ------------------------------------------------------------------------------------------------
# Timing helpers
# ------------------------------------------------------------------------------------------------


def compile_and_time(fn: Callable, args: tuple, reps: int) -> tuple[Any, float, float, Any]:
    """(compiled, compile seconds, seconds per run (best of the warm-up and reps), last output).

    Runs slower than 5 s are not repeated (the warm-up run is the measurement).
    """
    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    t_compile = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = jax.block_until_ready(compiled(*args))
    best = time.perf_counter() - t0
    for _ in range(reps if best < 5.0 else 0):
        t0 = time.perf_counter()
        out = jax.block_until_ready(compiled(*args))
        best = min(best, time.perf_counter() - t0)
    return compiled, t_compile, best, out


def _optimize(cfg: Config, model: LatentModel, params: Any, ctx: Any, key: jax.Array, unroll: bool):
    """One cold planning call; returns metrics."""
    prob = make_problem(cfg, model, params, ctx)
    if cfg.planner.kind in COLLOCATION:
        plan = collocation.init_plan(cfg, prob, key, ACTION_DIM)
        return collocation.optimize(cfg, prob, plan, key=key, unroll=unroll)[1]
    state = shooting.init_shoot(cfg, ACTION_DIM)
    return shooting.optimize_shoot(cfg, prob, state, key, unroll=unroll)[1]


def flops_per_call(
    cfg: Config, model: LatentModel, params: Any, ctx: Any, keys: jax.Array
) -> float:
    """Matmul FLOPs of one call over the batch, every loop (CEM iterations, horizon rollouts,
    collocation and CG iterations) counted per iteration (:mod:`mjx_collo.flops`; XLA's cost
    analysis counts a loop body once and under-reported the CEM start ~30x)."""
    fn = jax.vmap(lambda ctx_, key_: _optimize(cfg, model, params, ctx_, key_, False))
    return matmul_flops(fn, ctx, keys).flops


def _with_iters(cfg: Config, k: int) -> Config:
    pc = cfg.planner
    if pc.kind in COLLOCATION:
        return cfg.model_copy(update={"planner": pc.model_copy(update={"iters": k})})
    sh = pc.shooting.model_copy(update={"iters": k})
    return cfg.model_copy(update={"planner": pc.model_copy(update={"shooting": sh})})


def _iters(cfg: Config) -> int:
    pc = cfg.planner
    return pc.iters if pc.kind in COLLOCATION else pc.shooting.iters


# ------------------------------------------------------------------------------------------------
# Section: per-call cost
# ------------------------------------------------------------------------------------------------

# (label, method, overrides, outer iterations actually run per batch size; None = the full K).
# Runs with fewer iterations are extrapolated linearly in K (marked ``extrap``).
# The collocation rows plan without a policy prior (this bench builds no actor): the first two with
# the CEM 30 x 6 start and 50 steps of the default before 2026-12-07 (and of --preset paper), the
# third with today's default's search behind its prior's proposal (CEM 30 x 3, 10 steps).
CEM_START = ["planner.init=cem", "planner.iters=50", "planner.init_cem.iters=6"]
CALLS: list[tuple[str, str, list[str], dict[int, int | None]]] = [
    ("collodreamer/adam (CEM 30x6 start, K=50)", "collodreamer", CEM_START, {1: None, 16: None}),
    (
        "collodreamer/adam, end bootstrap (value_lambda=1)",
        "collodreamer",
        CEM_START + ["planner.value_lambda=1"],
        {1: None, 16: None},
    ),
    (
        "collodreamer/adam (default's search: CEM 30x3, K=10, no prior)",
        "collodreamer",
        ["planner.init=cem"],
        {1: None, 16: None},
    ),
    (
        "collodreamer/adam cold K=200 (older default)",
        "collodreamer",
        ["planner.init=rollout", "planner.iters=200", "planner.value_lambda=1"],
        {1: None, 16: None},
    ),
    (
        "collodreamer/cg",
        "collodreamer",
        ["planner.solver=cg", "planner.iters=30", "planner.init=rollout", "planner.value_lambda=1"],
        {1: None, 16: 5},
    ),
    (
        "collodreamer/gauss_newton",
        "collodreamer",
        [
            "planner.solver=gauss_newton",
            "planner.iters=30",
            "planner.init=rollout",
            "planner.value_lambda=1",
        ],
        {1: 5, 16: 2},
    ),
    ("latco/adam", "latco", [], {1: None, 16: None}),
    (
        "latco/cg",
        "latco",
        ["planner.solver=cg", "planner.iters=30", "planner.init=rollout"],
        {1: None, 16: 5},
    ),
    (
        "latco/gauss_newton exact LC (K=100)",
        "latco",
        [
            "planner.solver=gauss_newton",
            "planner.step_control=none",
            "planner.iters=100",
            "planner.warm_start=false",
            "planner.init=random",
            "planner.init_std=1.0",
        ],
        {1: None, 16: 2},
    ),
    (
        "latco/gauss_newton exact LC, gaussian full",
        "latco",
        [
            "planner.solver=gauss_newton",
            "planner.step_control=none",
            "planner.iters=100",
            "planner.warm_start=false",
            "planner.init=random",
            "planner.init_std=1.0",
            "planner.space=full",
            "wm.latent=gaussian",
            "wm.stoch=30",
            "wm.gru_layernorm=false",
        ],
        {1: 2, 16: 2},
    ),
    ("cem (1000 samples)", "cem", [], {1: 1, 16: 1}),
    ("mppi (1000 samples)", "mppi", [], {1: 1, 16: 1}),
    ("mppi_value (H=3)", "mppi_value", [], {1: None, 16: None}),
]


_FLOPS_PER_ENV: dict[str, float] = {}
FLOP_COUNT = "matmul FLOPs, every loop counted per iteration (mjx_collo.flops)"


def _call_row(label: str, method: str, overrides: list[str], batch: int, run_k: int | None):
    cfg = load(method, overrides)
    model, params = build(cfg, jax.random.PRNGKey(0))
    ctx = contexts(cfg, params, jax.random.PRNGKey(1), batch)
    keys = jax.random.split(jax.random.PRNGKey(2), batch)
    k_full = _iters(cfg)
    run_k = k_full if run_k is None else min(run_k, k_full)
    c_run = _with_iters(cfg, run_k)

    def one(ctx_: Any, key_: jax.Array) -> dict[str, jax.Array]:
        return _optimize(c_run, model, params, ctx_, key_, False)

    reps = 2 if run_k == k_full else 1
    _, t_comp, t_run, metrics = compile_and_time(jax.vmap(one), (ctx, keys), reps)
    t_call = t_run * k_full / run_k
    if label not in _FLOPS_PER_ENV:  # per-env FLOPs do not depend on the vmapped batch size
        one = jax.tree.map(lambda x: x[:1], (ctx, keys))
        _FLOPS_PER_ENV[label] = flops_per_call(cfg, model, params, *one)
    flops = _FLOPS_PER_ENV[label] * batch
    m = {k: float(np.mean(v)) for k, v in metrics.items()}
    full = run_k == k_full
    return {
        "planner": label,
        "method": method,
        "overrides": overrides,
        "solver": cfg.planner.solver if method in COLLOCATION else "-",
        "space": cfg.planner.space,
        "latent": cfg.wm.latent,
        "horizon": cfg.planner.horizon,
        "iters": k_full,
        "iters_run": run_k,
        "extrapolated": not full,
        "batch": batch,
        "compile_s": t_comp,
        "ms_per_call_per_env": 1e3 * t_call / batch,
        "gflop_per_call_per_env": flops / batch / 1e9,
        "gflops_per_s": flops / t_call / 1e9,
        "flop_count": FLOP_COUNT,
        "iters_to_feasible": m["iters_to_feasible"] if full else None,
        "dyn_viol": m["dyn_viol"] if full else None,
        "act_viol": m["act_viol"] if full else None,
        "shadow_return": m["shadow_return"] if full else None,
    }


def bench_calls(batches: tuple[int, ...], only: str) -> list[dict[str, Any]]:
    rows = []
    for label, method, overrides, runs in CALLS:
        if not _selected(label, only):
            continue
        for batch in batches:
            row = _call_row(label, method, overrides, batch, runs[batch])
            rows.append(row)
            _print_call(row)
    return rows


def _print_call(r: dict[str, Any]) -> None:
    full = not r["extrapolated"]
    itf = f"{r['iters_to_feasible']:.0f}" if full else "-"
    viol = f"{r['dyn_viol']:.1e}" if full else "-"
    print(
        f"{r['planner']:<44} B={r['batch']:<3} K={r['iters']:<4}"
        f" {r['ms_per_call_per_env']:>9.1f} ms/call/env {'' if full else 'extrap':<6}"
        f" compile {r['compile_s']:>5.1f}s {r['gflop_per_call_per_env']:>8.2f} GFLOP/call/env"
        f" {r['gflops_per_s']:>5.1f} GFLOP/s  feasible@{itf:>4}  viol {viol}",
        flush=True,
    )


# ------------------------------------------------------------------------------------------------
# Section: return per CPU second (MPC inside the model)
# ------------------------------------------------------------------------------------------------

# The MPC comparison uses the LatCo objective (rewards only): with random weights the value net is
# not a correct value, and chasing it would not show up in the executed reward.
# Rows start from small random actions (planner.init=rollout), as they were measured before the
# default became the CEM start.
COLD = ["planner.init=rollout"]
OLD = [*COLD, "planner.iters=30", "planner.adam_lr=0.05", "planner.warm_start=true"]  # pre-a67d95a
MPC: list[tuple[str, str, list[str]]] = [
    ("random actions (no planning)", "latco", [*COLD, "planner.iters=0"]),
    ("adam K=200 lr 0.015 cold", "latco", [*COLD, "planner.iters=200"]),
    ("adam K=30 lr 0.05 warm (old default)", "latco", OLD),
    ("adam K=15 lr 0.05 warm", "latco", [*OLD, "planner.iters=15"]),
    ("adam K=30 lr 0.05 cold", "latco", [*OLD, "planner.warm_start=false"]),
    ("adam K=100 lr 0.05 warm", "latco", [*OLD, "planner.iters=100"]),
    (
        "cg K=10 cg_iters=3 warm",
        "latco",
        [
            *COLD,
            "planner.solver=cg",
            "planner.iters=10",
            "planner.cg_iters=3",
            "planner.warm_start=true",
        ],
    ),
    (
        "cg K=30 cg_iters=3 warm",
        "latco",
        [
            *COLD,
            "planner.solver=cg",
            "planner.iters=30",
            "planner.cg_iters=3",
            "planner.warm_start=true",
        ],
    ),
]


def mpc_episode(cfg: Config, model: LatentModel, params: Any, rounds: int) -> Callable:
    """f(ctx, key) -> (executed return, mean dyn violation) of MPC inside the model."""
    planner = make_planner(cfg, model, ACTION_DIM)
    m = cache_len(cfg)

    def run(ctx: wm.RSSMState, key: jax.Array):
        state = mpc_init(planner, params, ctx, key)

        def round_(carry, k):
            ctx, st = carry
            st, metrics = replan(planner, params, ctx, st, k)

            def act(c, kk):
                ctx, st = c
                a, st = next_action(cfg, st, kk, training=False)
                ctx = wm.img_step_mean(cfg.wm, params[0], ctx, a)
                r = wm.reward(cfg.wm, params[0], wm.get_feat(ctx))
                return (ctx, st), r

            (ctx, st), rs = jax.lax.scan(act, (ctx, st), jax.random.split(k, m))
            return (ctx, st), (jnp.sum(rs), metrics["dyn_viol"])

        _, (rets, viol) = jax.lax.scan(round_, (ctx, state), jax.random.split(key, rounds))
        return jnp.sum(rets), jnp.mean(viol)

    return jax.vmap(run)


def bench_mpc(
    batch: int, rounds: int, only: str, configs: list[tuple[str, str, list[str]]] | None = None
) -> list[dict[str, Any]]:
    """Runs the MPC configurations; returns are also reported paired against the first row
    (the same start states and keys for every configuration)."""
    rows: list[dict[str, Any]] = []
    base: np.ndarray | None = None
    for label, method, overrides in configs or MPC:
        if not _selected(label, only) and rows:
            continue
        # LatCo's 15 actions per call, as the recorded rows were measured (the default is now 5)
        cfg = load(method, ["planner.mpc_steps=15"] + overrides)
        model, params = build(cfg, jax.random.PRNGKey(0))
        ctx = contexts(cfg, params, jax.random.PRNGKey(1), batch)
        keys = jax.random.split(jax.random.PRNGKey(3), batch)
        if cfg.planner.iters == 0:
            fn = _random_episode(cfg, params, rounds)
        else:
            fn = mpc_episode(cfg, model, params, rounds)
        _, t_comp, t_run, (ret, viol) = compile_and_time(fn, (ctx, keys), reps=2)
        gflop = 0.0
        if cfg.planner.iters > 0:  # deterministic cost axis (wall time moves with the CPU's load)
            one = jax.tree.map(lambda x: x[:1], (ctx, keys))
            gflop = flops_per_call(cfg, model, params, *one) / 1e9
        ret = np.asarray(ret)
        base = ret if base is None else base
        diff = ret - base
        row = {
            "config": label,
            "method": method,
            "overrides": overrides,
            "batch": batch,
            "steps": rounds * cache_len(cfg),
            "compile_s": t_comp,
            "plan_s_per_env": t_run / batch,
            "ms_per_call_per_env": 1e3 * t_run / batch / rounds,
            "gflop_per_call_per_env": gflop,
            "return_mean": float(np.mean(ret)),
            "gain_vs_first": float(np.mean(diff)),
            "gain_sem": float(np.std(diff) / np.sqrt(batch)),
            "dyn_viol": float(np.mean(viol)),
        }
        rows.append(row)
        print(
            f"{label:<30} {gflop:>6.2f} GFLOP/call/env {row['ms_per_call_per_env']:>7.1f} ms  return "
            f"{row['return_mean']:8.3f}  gain {row['gain_vs_first']:+7.3f} ± {row['gain_sem']:.3f}"
            f"  viol {row['dyn_viol']:.2e}  (compile {t_comp:.1f}s)",
            flush=True,
        )
    return rows


def _random_episode(cfg: Config, params: Any, rounds: int) -> Callable:
    steps = rounds * cache_len(cfg)

    def run(ctx: wm.RSSMState, key: jax.Array):
        acts = jax.random.uniform(key, (steps, ACTION_DIM), minval=-1.0, maxval=1.0)

        def act(c, a):
            c = wm.img_step_mean(cfg.wm, params[0], c, a)
            return c, wm.reward(cfg.wm, params[0], wm.get_feat(c))

        _, rs = jax.lax.scan(act, ctx, acts)
        return jnp.sum(rs), jnp.zeros(())

    return jax.vmap(run)


# ------------------------------------------------------------------------------------------------


def _selected(label: str, only: str) -> bool:
    return not only or any(label.startswith(p) for p in only.split(","))


def _merge(old: list[dict], new: list[dict], key: tuple[str, ...]) -> list[dict]:
    """Rows of ``new`` replace rows of ``old`` with the same key (partial reruns with --only)."""
    fresh = {tuple(r[k] for k in key) for r in new}
    return [r for r in old if tuple(r[k] for k in key) not in fresh] + new


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--section", choices=["calls", "mpc", "all"], default="all")
    parser.add_argument("--batches", default="1,16", help="env batch sizes for the calls table")
    parser.add_argument(
        "--only", default="", help="comma-separated: run only labels starting with one of these"
    )
    parser.add_argument("--out", default=str(ROOT / "bench_results" / "planner.json"))
    parser.add_argument(
        "--recount",
        action="store_true",
        help="recompute the GFLOP columns of the stored rows (deterministic; keeps their times)",
    )
    args = parser.parse_args()
    if args.recount:
        recount(Path(args.out))
        return
    out: dict[str, Any] = {
        "device": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "jax": jax.__version__,
        "action_dim": ACTION_DIM,
    }
    path = Path(args.out)
    if path.exists():
        out = {**json.loads(path.read_text()), **out}
    peak = matmul_peak()
    print(f"matmul ceiling now: {peak:.1f} GFLOP/s (1024^3 f32; the CPU is shared, so this moves)")
    if args.section in ("calls", "all"):
        print("== per planning call (H=30, cold start)")
        rows = bench_calls(tuple(int(b) for b in args.batches.split(",")), args.only)
        for r in rows:
            r["matmul_gflops_at_run"] = peak
            r["fraction_of_matmul"] = r["gflops_per_s"] / peak
        out["calls"] = _merge(out.get("calls", []), rows, ("planner", "batch"))
    if args.section in ("mpc", "all"):
        print("== return per CPU second: 60-step MPC inside the model, 16 envs")
        rows = bench_mpc(16, 4, args.only)
        for r in rows:
            r["matmul_gflops_at_run"] = peak
        out["mpc"] = _merge(out.get("mpc", []), rows, ("config",))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1))
    _summary(out)
    print(f"wrote {path}")


def recount(path: Path) -> None:
    """GFLOP columns of the rows in ``path`` recomputed with the current counter; the measured
    times stay (FLOP counts do not depend on the machine or its load)."""
    out = json.loads(path.read_text())
    calls = {label: (method, ov) for label, method, ov, _ in CALLS}
    for r in out.get("calls", []):
        if r["planner"] not in calls:
            continue
        method, ov = calls[r["planner"]]
        cfg = load(method, ov)
        model, params = build(cfg, jax.random.PRNGKey(0))
        one = (
            contexts(cfg, params, jax.random.PRNGKey(1), 1),
            jax.random.split(jax.random.PRNGKey(2), 1),
        )
        old = r["gflop_per_call_per_env"]
        r["gflop_per_call_per_env"] = flops_per_call(cfg, model, params, *one) / 1e9
        r["gflops_per_s"] = r["gflop_per_call_per_env"] / (r["ms_per_call_per_env"] / 1e3)
        if r.get("matmul_gflops_at_run"):
            r["fraction_of_matmul"] = r["gflops_per_s"] / r["matmul_gflops_at_run"]
        r["flop_count"] = FLOP_COUNT
        print(
            f"{r['planner']:<50} batch {r['batch']:>2}: {old:8.2f} -> {r['gflop_per_call_per_env']:8.2f} GFLOP/call/env"
        )
    for r in out.get("mpc", []):
        if not r.get("gflop_per_call_per_env"):
            continue
        cfg = load(r["method"], ["planner.mpc_steps=15"] + r["overrides"])
        model, params = build(cfg, jax.random.PRNGKey(0))
        one = (
            contexts(cfg, params, jax.random.PRNGKey(1), 1),
            jax.random.split(jax.random.PRNGKey(3), 1),
        )
        r["gflop_per_call_per_env"] = flops_per_call(cfg, model, params, *one) / 1e9
        r["flop_count"] = FLOP_COUNT
    path.write_text(json.dumps(out, indent=1))
    print(f"wrote {path}")


def _summary(out: dict[str, Any]) -> None:
    """Target check: default ColloDreamer planner <= 100 ms per call per env at 16 envs."""
    rows = [r for r in out.get("calls", []) if "(default)" in r["planner"] and r["batch"] == 16]
    for r in rows:
        need = r["gflop_per_call_per_env"] / 0.1
        verdict = "meets" if r["ms_per_call_per_env"] <= 100 else "misses"
        print(
            f"target: default planner {r['ms_per_call_per_env']:.0f} ms/call/env at 16 envs "
            f"({verdict} 100 ms); {r['gflop_per_call_per_env']:.2f} GFLOP/call/env needs "
            f"{need:.0f} GFLOP/s for 100 ms; matmul ceiling at that run "
            f"{r.get('matmul_gflops_at_run', float('nan')):.0f} GFLOP/s"
        )


if __name__ == "__main__":
    main()

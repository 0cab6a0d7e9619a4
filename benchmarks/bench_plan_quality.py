"""Planner quality on a *trained* world model (``make bench-plan-quality``).

Why this exists: ``bench_planner.py`` measures planners on random-weight models, and on those 30
warm-started Adam steps looked best per CPU second. On a trained model that setting does not plan at
all (cheetah eval return 3, random-policy level, against 92 for CEM on the same model), which is why
ColloDreamer and LatCo did not learn. Every planner default must be checked here.

Fixture: ``benchmarks/fixtures/cheetah_cem_20k.npz`` — the world-model parameters (default
categorical RSSM) of ``train.py --env cheetah --method cem --steps 20000 run.eval_every=100000``
(CEM reached a training return of 114 at 20k env steps) and the first 6000 replay rows of that run,
written by ``benchmarks/dump_model.py``. CEM's model is used because CEM learns with it: a planner
that fails on it fails at planning, not because the model is poor.

Sections (both report every configuration side by side):
  model  Cold planning calls from 16 contexts (posteriors filtered along the replay). Reports the
         *shadow return*: the undiscounted model reward of the plan's clipped actions rolled out
         through the model (what the plan really achieves; a collocation plan's own return can be
         far higher when it violates the dynamics), the same for its initial actions, the plan's own
         return, its dynamics violation, and ms per call per context (16 vmapped).
  env    Real-env MPC returns: ``--episodes`` deterministic cheetah episodes (``trainer.evaluate``)
         with the fixture's world model, exactly as a training run evaluates.

Writes ``bench_results/plan_quality.json``. Run parts with ``--section model`` or
``--only <name>``; ``--list`` prints the configurations.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import jax
import numpy as np

import envs
from mjx_collo import config, parallel, plan_quality
from mjx_collo import trainer as trainer_lib
from mjx_collo.plan_quality import contexts, load_params

ROOT = Path(__file__).resolve().parent.parent
FIXTURE = ROOT / "benchmarks" / "fixtures" / "cheetah_cem_20k.npz"
OUT = ROOT / "bench_results" / "plan_quality.json"
TASK = "cheetah_run"

# name -> (method, overrides). The reward-only objective everywhere (the fixture has no trained
# value), so ColloDreamer's collocation runs with value.bootstrap=false, and the fixture's MSE
# reward head. The fixture has no policy prior either: the rows plan with the planner alone, with
# the settings of the default of their time (CEM 30 x 6 start, 50 Adam steps), which the default
# ColloDreamer left on 2026-12-07 for a prior's proposal + CEM 30 x 3 + 10 steps.
NO_VALUE = [
    "value.bootstrap=false",
    "wm.reward_head=mse",
    "planner.init=cem",
    "planner.iters=50",
    "planner.init_cem.iters=6",
]
# Rows other than the default start from small random actions (planner.init=rollout), as they
# were measured before the default became the CEM start (planner.init=cem, 50 iterations).
COLD = NO_VALUE + ["planner.init=rollout"]


def _cem_overrides(samples: int, iters: int) -> list[str]:
    """A CEM start of ``samples`` x ``iters`` with 10% elites, as ``planner.init_cem`` overrides."""
    cem = ["planner.init_cem.samples", "planner.init_cem.elites", "planner.init_cem.iters"]
    values = (samples, max(samples // 10, 1), iters)
    return [f"{k}={v}" for k, v in zip(cem, values, strict=True)]


CEM_100X4 = _cem_overrides(100, 4)  # the previous default's start
CONFIGS: dict[str, tuple[str, list[str]]] = {
    "collocation default": ("collodreamer", NO_VALUE),  # the planner alone, CEM 30 x 6 + K=50
    # today's default's search without its prior's proposal: CEM 30 x 3 + K=10
    "lean planner alone (cem 30x3, K=10)": (
        "collodreamer",
        NO_VALUE + ["planner.init_cem.iters=3", "planner.iters=10"],
    ),
    "adam K=200 lr=0.015 cold (old default)": ("collodreamer", COLD + ["planner.iters=200"]),
    "adam K=30 lr=0.05 warm (older default)": (
        "collodreamer",
        COLD + ["planner.iters=30", "planner.adam_lr=0.05", "planner.warm_start=true"],
    ),
    "adam K=300 lr=0.01": (
        "collodreamer",
        COLD + ["planner.iters=300", "planner.adam_lr=0.01"],
    ),
    "adam K=200 lr=0.015 warm": (
        "collodreamer",
        COLD + ["planner.iters=200", "planner.warm_start=true"],
    ),
    # A tighter dynamics tolerance plans worse: the relaxation is what lets Adam move.
    "adam K=200 dyn_eps=1e-3": (
        "collodreamer",
        COLD + ["planner.iters=200", "planner.dyn_eps=1e-3"],
    ),
    "adam K=200 dyn_eps=1e-4": (
        "collodreamer",
        COLD + ["planner.iters=200", "planner.dyn_eps=1e-4"],
    ),
    # Half the iterations at any step size plans far worse: the multipliers tighten per iteration.
    "adam K=100 lr=0.03": (
        "collodreamer",
        COLD + ["planner.iters=100", "planner.adam_lr=0.03"],
    ),
    "adam K=100 lr=0.05 decay=0.1": (
        "collodreamer",
        COLD + ["planner.iters=100", "planner.adam_lr=0.05", "planner.adam_decay=0.1"],
    ),
    "gauss_newton K=30": (
        "collodreamer",
        COLD + ["planner.solver=gauss_newton", "planner.iters=30"],
    ),
    # Matrix-free Gauss-Newton: 10 conjugate-gradient steps per iteration instead of the exact solve.
    "cg K=30": ("collodreamer", COLD + ["planner.solver=cg", "planner.iters=30"]),
    "cg K=15": ("collodreamer", COLD + ["planner.solver=cg", "planner.iters=15"]),
    # Shooting refinement: Adam on the actions through the model rollout after collocation.
    "adam K=200 + refine 50": (
        "collodreamer",
        COLD + ["planner.iters=200", "planner.refine_iters=50"],
    ),
    "refine 100 only (shooting GD)": (
        "collodreamer",
        COLD + ["planner.iters=0", "planner.refine_iters=100"],
    ),
    "adam K=100 + refine 50": (
        "collodreamer",
        COLD + ["planner.iters=100", "planner.adam_lr=0.03", "planner.refine_iters=50"],
    ),
    # Collocation started from a small CEM on the same objective (the default: 30x6, K=50; these
    # two rows were measured with the previous default's 100x4 start, which they pin).
    "cem init 100x4 only (K=0)": ("collodreamer", NO_VALUE + CEM_100X4 + ["planner.iters=0"]),
    # Other CEM starts (samples x iterations, elites 10%; added below): the 100x4 start was 80% of
    # the previous default call's matmul FLOPs (bench_planner).
    "collocation default, K=25": ("collodreamer", NO_VALUE + CEM_100X4 + ["planner.iters=25"]),
    "cem 100x4": (
        "cem",
        ["planner.shooting.samples=100", "planner.shooting.elites=10", "planner.shooting.iters=4"],
    ),
    "cem 300x5": (
        "cem",
        ["planner.shooting.samples=300", "planner.shooting.elites=30", "planner.shooting.iters=5"],
    ),
}


def _cem_start(samples: int, iters: int) -> tuple[str, list[str]]:
    """The default collocation after a CEM start of ``samples`` x ``iters`` (elites 10%)."""
    return "collodreamer", NO_VALUE + _cem_overrides(samples, iters)


CONFIGS.update(
    {
        f"collocation default, cem init {n}x{k}": _cem_start(n, k)
        for n, k in ((100, 4), (50, 4), (100, 2), (50, 2), (50, 6), (30, 6), (30, 8), (20, 10))
    }
)

# One cold call per context cannot show a warm start: these only run in the env section.
ENV_ONLY = {"adam K=200 lr=0.015 warm"}


def load_cfg(method: str, overrides: list[str], episodes: int = 4) -> config.Config:
    # The env section executes LatCo's 15 actions per planning call, as the recorded rows were
    # measured (the training default is now 5; the model section is one call and unaffected).
    base = [f"run.eval_episodes={episodes}", "planner.mpc_steps=15"]
    return config.load(task=TASK, method=method, overrides=base + overrides)


def model_section(name: str, method: str, overrides: list[str], params, ctxs) -> dict:
    row = plan_quality.measure(load_cfg(method, overrides), params, ctxs)
    row = {"config": name, "method": method, "overrides": overrides, **row}
    ms, gflop = row["ms_per_call_per_ctx"], row["gflop_per_call"]
    print(
        f"  {name:<40} shadow {row['shadow_return']:6.2f} ± {row['shadow_return_sem']:.2f} "
        f"(initial {row['initial_shadow_return']:.2f}, plan {row['plan_return']:6.2f}, "
        f"viol {row['dyn_viol']:.3f})  {ms:7.1f} ms/call/ctx  {gflop:6.2f} GFLOP/call",
        flush=True,
    )
    return row


def env_section(name: str, method: str, overrides: list[str], params, episodes: int) -> dict:
    cfg = load_cfg(method, overrides, episodes)
    env = envs.from_config(cfg.env)
    trainer = trainer_lib.make_train(cfg, env)
    _, hyper, _ = parallel.sweep_grid({}, 1)
    hyper = jax.tree.map(lambda x: x[0], hyper)
    state = jax.jit(trainer.init)(jax.random.PRNGKey(0), hyper).replace(wm=params)
    key = jax.random.PRNGKey(1)
    t = time.perf_counter()
    fn = jax.jit(trainer.evaluate).lower(state, key).compile()
    compile_s = time.perf_counter() - t
    t = time.perf_counter()
    returns = np.asarray(jax.block_until_ready(fn(state, key))["returns"])
    run_s = time.perf_counter() - t
    row = {
        "config": name,
        "method": method,
        "overrides": overrides,
        "returns": returns.tolist(),
        "return_mean": float(returns.mean()),
        "return_std": float(returns.std()),
        "compile_s": compile_s,
        "s_per_episode_batch": run_s,
    }
    print(
        f"  {name:<40} return {row['return_mean']:6.1f} ± {row['return_std']:.1f} "
        f"over {episodes} episodes  ({run_s:.0f} s for the vmapped batch)",
        flush=True,
    )
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--section", choices=["model", "env", "all"], default="all")
    ap.add_argument("--only", action="append", help="configuration name (repeatable)")
    ap.add_argument("--episodes", type=int, default=4)
    ap.add_argument("--fixture", type=Path, default=FIXTURE)
    ap.add_argument("--list", action="store_true")
    args = ap.parse_args(argv)
    if args.list:
        for name, (method, ov) in CONFIGS.items():
            print(f"{name}: --method {method} {' '.join(ov)}")
        return 0
    names = args.only or list(CONFIGS)
    unknown = [n for n in names if n not in CONFIGS]
    if unknown:
        raise SystemExit(f"unknown configuration(s) {unknown}; see --list")
    base = load_cfg("collodreamer", NO_VALUE)
    params, replay = load_params(base, args.fixture)
    result = json.loads(OUT.read_text()) if OUT.exists() else {}
    result.update({"fixture": str(args.fixture.relative_to(ROOT)), "cpu_count": os.cpu_count()})
    if args.section in ("model", "all"):
        print("model: cold planning calls from 16 replay contexts (reward-only objective, H=30)")
        ctxs = contexts(base, params, replay)
        rows = [model_section(n, *CONFIGS[n], params, ctxs) for n in names if n not in ENV_ONLY]
        _merge(result, "model", rows)
    if args.section in ("env", "all"):
        print(f"env: real cheetah episodes with MPC on the fixture model ({args.episodes} vmapped)")
        rows = [env_section(n, *CONFIGS[n], params, args.episodes) for n in names]
        _merge(result, "env", rows)
    OUT.parent.mkdir(exist_ok=True)
    OUT.write_text(json.dumps(result, indent=1))
    print(f"wrote {OUT.relative_to(ROOT)}")
    return 0


def _merge(result: dict, section: str, rows: list[dict]) -> None:
    """Rows of a partial rerun replace the old rows of the same configuration."""
    names = {r["config"] for r in rows}
    result[section] = [r for r in result.get(section, []) if r["config"] not in names] + rows


if __name__ == "__main__":
    raise SystemExit(main())

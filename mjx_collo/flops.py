"""Matmul FLOPs of a JAX function, with every loop counted as many times as it runs.

XLA's ``compiled.cost_analysis()`` counts a while-loop body once, so for programs built from
``lax.scan`` / ``fori_loop`` (a planning call: CEM iterations over horizon rollouts; a chunk:
thousands of env steps) it reports the FLOPs of a single iteration. This module walks the jaxpr
instead and counts the FLOPs of ``dot_general`` and ``conv_general_dilated`` (the matmuls, which
dominate every network here), multiplying each ``scan`` body by its length. Elementwise work is
not counted, so the figure is the one to compare with a matmul peak.

Two constructs have no static trip count, and the result records how they were counted:
  * ``cond`` / ``switch``: the most expensive branch (an upper bound: ``branches`` counts them);
  * ``while`` loops with a data-dependent trip count: the body once (a lower bound: ``while``
    counts them). ``fori_loop`` with static bounds lowers to ``scan`` and is counted exactly.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import jax
import jax.numpy as jnp
from jax.extend import core as jcore


@dataclass
class FlopCount:
    """Matmul FLOPs of one call, and how many inexact constructs went into the figure."""

    flops: float = 0.0
    branches: int = 0  # cond/switch eqns counted at their most expensive branch (upper bound)
    whiles: int = 0  # while loops counted once (lower bound)
    by_primitive: dict[str, float] = field(default_factory=dict)

    @property
    def gflops(self) -> float:
        return self.flops / 1e9

    @property
    def exact(self) -> bool:
        return self.branches == 0 and self.whiles == 0


def _dot_flops(eqn: Any) -> float:
    (lc, _rc), _ = eqn.params["dimension_numbers"]
    lhs = eqn.invars[0].aval.shape
    out = eqn.outvars[0].aval.shape
    return 2.0 * math.prod(out) * math.prod(lhs[d] for d in lc)


def _window_hits(n: int, lhs_dil: int, lo: int, k: int, rhs_dil: int, stride: int, o: int) -> int:
    """(output position, kernel tap) pairs of one spatial dim whose input is a real element, not
    padding or a zero inserted by input dilation."""
    last = (n - 1) * lhs_dil
    hits = 0
    for out in range(o):
        for tap in range(k):
            pos = out * stride + tap * rhs_dil - lo
            hits += 0 <= pos <= last and pos % lhs_dil == 0
    return hits


def _conv_flops(eqn: Any) -> float:
    """Multiply-adds x 2 that touch real input: a transposed conv (the input gradient of a strided
    one) is not charged for the zeros it inserts, nor any conv for its padding."""
    lhs = eqn.invars[0].aval.shape
    rhs = eqn.invars[1].aval.shape
    out = eqn.outvars[0].aval.shape
    p = eqn.params
    dn = p["dimension_numbers"]
    spatial = len(dn.lhs_spec) - 2
    lhs_dil = p.get("lhs_dilation") or (1,) * spatial
    rhs_dil = p.get("rhs_dilation") or (1,) * spatial
    taps = 1
    for i in range(spatial):
        taps *= _window_hits(
            lhs[dn.lhs_spec[2 + i]],
            lhs_dil[i],
            p["padding"][i][0],
            rhs[dn.rhs_spec[2 + i]],
            rhs_dil[i],
            p["window_strides"][i],
            out[dn.out_spec[2 + i]],
        )
    # per (output batch, output feature): in_features / groups x the taps that hit input
    return 2.0 * out[dn.out_spec[0]] * out[dn.out_spec[1]] * rhs[dn.rhs_spec[1]] * taps


def _as_jaxpr(x: Any) -> Any:
    return x.jaxpr if isinstance(x, jcore.ClosedJaxpr) else x


def _sub_jaxprs(params: dict[str, Any]) -> list[Any]:
    found = []
    for v in params.values():
        for item in v if isinstance(v, (tuple, list)) else (v,):
            if isinstance(item, (jcore.ClosedJaxpr, jcore.Jaxpr)):
                found.append(_as_jaxpr(item))
    return found


def _count(jaxpr: Any, acc: FlopCount, scale: float) -> float:
    total = 0.0
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        p = eqn.params
        if name == "dot_general":
            f = _dot_flops(eqn)
            acc.by_primitive[name] = acc.by_primitive.get(name, 0.0) + f * scale
        elif name == "conv_general_dilated":
            f = _conv_flops(eqn)
            acc.by_primitive[name] = acc.by_primitive.get(name, 0.0) + f * scale
        elif name == "scan":
            n = float(p["length"])
            f = n * _count(_as_jaxpr(p["jaxpr"]), acc, scale * n)
        elif name == "cond":
            acc.branches += 1
            costs = [_count(_as_jaxpr(b), FlopCount(), 1.0) for b in p["branches"]]
            best = max(range(len(costs)), key=costs.__getitem__)
            f = _count(_as_jaxpr(p["branches"][best]), acc, scale)
        elif name == "while":
            acc.whiles += 1
            f = _count(_as_jaxpr(p["body_jaxpr"]), acc, scale)
            f += _count(_as_jaxpr(p["cond_jaxpr"]), acc, scale)
        elif name in ("custom_jvp_call", "custom_vjp_call", "custom_vjp_call_jaxpr"):
            inner = p.get("call_jaxpr", p.get("fun_jaxpr"))
            f = _count(_as_jaxpr(inner), acc, scale)
        else:  # jit / pjit, remat, shard_map, closed_call, ...: the sub-programs run once each
            f = sum(_count(j, acc, scale) for j in _sub_jaxprs(p))
        total += f
    return total


def matmul_flops(fn: Callable, *args: Any, **kwargs: Any) -> FlopCount:
    """Matmul FLOPs of ``fn(*args, **kwargs)`` (traced abstractly: nothing is computed).

    Args may be arrays or ``jax.ShapeDtypeStruct``s; ``fn`` may be jitted or vmapped.
    """
    closed = jax.make_jaxpr(fn)(*args, **kwargs)
    acc = FlopCount()
    acc.flops = _count(closed.jaxpr, acc, 1.0)
    return acc


def matmul_peak() -> float:
    """GFLOP/s of a plain 1024^3 f32 matmul right now (the machine's achievable ceiling)."""
    a = jnp.ones((1024, 1024), jnp.float32)
    f = jax.jit(lambda x: x @ x)
    jax.block_until_ready(f(a))
    best = float("inf")
    for _ in range(5):
        t0 = time.perf_counter()
        jax.block_until_ready(f(a))
        best = min(best, time.perf_counter() - t0)
    return 2 * 1024**3 / best / 1e9


def matmul_budget(trainer, costs: dict[str, FlopCount]) -> dict[str, float]:
    """GFLOP of matmul work by schedule, from :attr:`Trainer.costs`: one planning call per env,
    one update, a steady chunk (after the prefill), one evaluation, and the whole run.

    Acting steps between planning calls (posterior filter, cached action) are not counted: next
    to a planning call they are negligible (for the Dreamer actor every step is counted).
    """
    run = trainer.cfg.run
    act, upd = costs["act"].gflops, costs["update"].gflops
    per_env = act / run.num_envs
    calls_per_chunk = trainer.iterations_per_chunk / trainer.plan_every
    updates_per_chunk = run.chunk_env_steps / run.train_every * run.train_steps
    chunk = calls_per_chunk * act + updates_per_chunk * upd
    evaluation = trainer.episode_agent_steps / trainer.plan_every * run.eval_episodes * per_env
    acting_steps = max(run.steps - run.prefill, 0)
    calls = acting_steps / (trainer.env_steps_per_iteration * trainer.plan_every)
    updates = run.pretrain + acting_steps / run.train_every * run.train_steps
    evals = run.steps // run.eval_every
    return {
        "plan_call_gflop_per_env": per_env,
        "update_gflop": upd,
        "chunk_gflop": chunk,
        "eval_gflop": evaluation,
        "run_gflop": calls * act + updates * upd + evals * evaluation,
        "run_planning_share": (calls * act + evals * evaluation)
        / max(calls * act + updates * upd + evals * evaluation, 1e-9),
    }


def cost_summary(compiled) -> dict[str, float]:
    """Memory of a compiled program (XLA memory analysis). Its FLOPs: :func:`matmul_budget`
    (XLA's cost analysis counts each loop body once)."""
    out: dict[str, float] = {}
    try:
        mem = compiled.memory_analysis()
        out["temp_mib"] = mem.temp_size_in_bytes / 2**20
        out["args_mib"] = mem.argument_size_in_bytes / 2**20
    except Exception:  # noqa: BLE001
        pass
    return out

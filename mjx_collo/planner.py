"""Planners behind one interface, and the MPC helpers the trainer calls.

``make_planner(cfg, model, action_dim)`` builds a :class:`Planner` for ``planner.kind``:

* ``latco`` / ``collodreamer``: latent collocation (docs/ALGORITHM.md §3, §4.1) with the primal solver
  ``planner.solver`` (``gauss_newton`` = exact LatCo, ``cg`` = matrix-free GN, ``adam``);
  ColloDreamer adds the discounted rewards and the frozen-value bootstrap; optionally
  (``planner.refine_iters``, off by default) the actions are then refined by Adam through the
  model rollout (shooting), see :func:`mjx_collo.planners.collocation.refine`;
* ``cem`` / ``mppi`` / ``mppi_value``: shooting baselines (§5).

Default solver (``adam``, 200 cold-started iterations at lr 0.015): chosen by plan quality per
CPU second on a *trained* world model (``benchmarks/bench_plan_quality.py``; fewer iterations or a
warm start plan markedly worse there). An Adam iteration costs one gradient (~2 forward passes of
the plan); a matrix-free GN iteration costs ~11x that and an exact GN iteration ~100x, while
LatCo's multipliers (x1.4 per iteration at most) need many outer iterations whatever the primal
step, so the cheap step wins at equal time.

Everything is pure and unbatched; the caller vmaps over envs (and seeds). The model is the
:class:`~mjx_collo.planners.protocol.LatentModel` protocol; nothing here imports the world model.

MPC (§3.5): :func:`replan` runs one planning call and refills the action cache of an
:class:`MPCState`; :func:`next_action` pops one action (exploration noise in training only, clipped
to [-1, 1]). *When* to replan is the trainer's decision, taken from an unbatched schedule counter
(a batched ``lax.cond`` predicate would run both branches), so neither function branches on
per-env state: the warm/cold choice and the non-finite fallback are element-wise selects.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from mjx_collo import value as value_lib
from mjx_collo.config import Config
from mjx_collo.planners import collocation, shooting
from mjx_collo.planners.collocation import PlanState
from mjx_collo.planners.objective import make_problem
from mjx_collo.planners.protocol import LatentModel, rollout
from mjx_collo.planners.shooting import ShootState

__all__ = [
    "COLLOCATION",
    "SHOOTING",
    "LatentModel",
    "MPCState",
    "PlanState",
    "Planner",
    "ShootState",
    "cache_len",
    "make_planner",
    "mpc_init",
    "mpc_reset",
    "next_action",
    "plan_value_batch",
    "replan",
    "replan_value",
    "shadow_batch",
]

COLLOCATION = ("latco", "collodreamer")
SHOOTING = ("cem", "mppi", "mppi_value")

Plan = PlanState | ShootState
Metrics = dict[str, jax.Array]
Inner = tuple[int, Callable[[Any, PlanState, jax.Array], Any], Any]


class Planner(NamedTuple):
    """Pure planner functions (unbatched).

    init: ``(params, ctx, key) -> plan`` cold plan; warm: ``(params, ctx, prev) -> plan`` previous
    plan shifted by ``cache_len`` steps (multipliers reset); optimize: ``(params, ctx, plan, key,
    inner) -> (plan, metrics, inner_state)``; actions: ``plan -> [H, A]`` (unclipped).
    """

    cfg: Config
    init: Callable[[Any, Any, jax.Array], Plan]
    warm: Callable[[Any, Any, Plan], Plan]
    optimize: Callable[..., tuple[Plan, Metrics, Any]]
    actions: Callable[[Plan], jax.Array]


def cache_len(cfg: Config) -> int:
    """Actions executed per planning call: min(horizon, mpc_steps)."""
    return min(cfg.planner.horizon, cfg.planner.mpc_steps)


def make_planner(cfg: Config, model: LatentModel, action_dim: int) -> Planner:
    """Planner for ``cfg.planner.kind`` over ``model`` with ``action_dim`` actions."""
    kind = cfg.planner.kind
    shift = cache_len(cfg)
    prob = lambda params, ctx: make_problem(cfg, model, params, ctx)
    if kind in COLLOCATION:

        def optimize(params, ctx, plan, key, inner: Inner | None = None):
            return collocation.optimize(cfg, prob(params, ctx), plan, inner, key)

        return Planner(
            cfg=cfg,
            init=lambda p, ctx, key: collocation.init_plan(cfg, prob(p, ctx), key, action_dim),
            warm=lambda p, ctx, prev: collocation.shift_plan(cfg, prob(p, ctx), prev, shift),
            optimize=optimize,
            actions=lambda plan: plan.a,
        )
    if kind in SHOOTING:

        def optimize_shoot(params, ctx, plan, key, inner: Inner | None = None):
            if inner is not None:
                raise ValueError("plan_inner value learning needs a collocation planner")
            plan, metrics = shooting.optimize_shoot(cfg, prob(params, ctx), plan, key)
            return plan, metrics, ()

        return Planner(
            cfg=cfg,
            init=lambda p, ctx, key: shooting.init_shoot(cfg, action_dim),
            warm=lambda p, ctx, prev: shooting.shift_shoot(cfg, prev, shift),
            optimize=optimize_shoot,
            actions=lambda plan: plan.mean,
        )
    raise ValueError(
        f"planner.kind={kind!r} has no planner (dreamer acts with mjx_collo.actor); "
        f"valid: {', '.join(COLLOCATION + SHOOTING)}"
    )


def _warm_start(cfg: Config) -> bool:
    pc = cfg.planner
    return pc.shooting.warm_start if pc.kind in SHOOTING else pc.warm_start


# ------------------------------------------------------------------------------------------------
# MPC
# ------------------------------------------------------------------------------------------------


@struct.dataclass
class MPCState:
    """Action cache of one env.

    actions: [M, A] clipped actions of the last plan (M = cache_len); pos: [] int32 index of the
    next action; plan: the last plan (warm start); has_plan: [] bool, False after init/reset or a
    non-finite plan (then the next call starts cold).
    """

    actions: jax.Array
    pos: jax.Array
    plan: Any
    has_plan: jax.Array


def mpc_init(planner: Planner, params: Any, ctx: Any, key: jax.Array) -> MPCState:
    """Empty cache (zeros) holding a cold plan for its structure."""
    plan = planner.init(params, ctx, key)
    acts = planner.actions(plan)
    m = cache_len(planner.cfg)
    return MPCState(
        actions=jnp.zeros((m, acts.shape[-1]), acts.dtype),
        pos=jnp.asarray(m, jnp.int32),
        plan=plan,
        has_plan=jnp.zeros((), bool),
    )


def mpc_reset(state: MPCState) -> MPCState:
    """Episode boundary: drop the cache and the warm-start plan."""
    return state.replace(
        actions=jnp.zeros_like(state.actions),
        pos=jnp.asarray(state.actions.shape[0], jnp.int32),
        has_plan=jnp.zeros((), bool),
    )


def _select(pred: jax.Array, a: Any, b: Any) -> Any:
    return jax.tree.map(lambda x, y: jnp.where(pred, x, y), a, b)


def _cache_tail(state: MPCState) -> jax.Array:
    """Unused part of the cache moved to the front, zero-padded; zeros if there is none. [M, A]"""
    m = state.actions.shape[0]
    idx = state.pos + jnp.arange(m)
    tail = jnp.where((idx < m)[:, None], state.actions[jnp.minimum(idx, m - 1)], 0.0)
    return jnp.where(state.has_plan, tail, 0.0)


def _replan(
    planner: Planner, params: Any, ctx: Any, state: MPCState, key: jax.Array, inner: Inner | None
) -> tuple[MPCState, Metrics, Any]:
    cfg = planner.cfg
    k_init, k_opt = jax.random.split(key)
    start = planner.init(params, ctx, k_init)
    if _warm_start(cfg):
        start = _select(state.has_plan, planner.warm(params, ctx, state.plan), start)
    plan, metrics, inner_state = planner.optimize(params, ctx, start, k_opt, inner)
    m = state.actions.shape[0]
    acts = jnp.clip(planner.actions(plan)[:m], -1.0, 1.0)
    ok = jnp.all(jnp.isfinite(acts))
    new = MPCState(
        actions=jnp.where(ok, acts, _cache_tail(state)),
        pos=jnp.zeros((), jnp.int32),
        plan=_select(ok, plan, start),
        has_plan=ok,
    )
    metrics = {**metrics, "nonfinite": (~ok).astype(jnp.float32)}
    return new, metrics, inner_state


def replan(
    planner: Planner, params: Any, ctx: Any, state: MPCState, key: jax.Array
) -> tuple[MPCState, Metrics]:
    """One planning call from context ``ctx``; refills the cache and resets its position.

    Warm start (``planner.warm_start`` / ``shooting.warm_start``) shifts the previous plan when
    there is one. Non-finite plan actions fall back to the unused tail of the previous cache (else
    zeros) and force the next call to start cold. Metrics: dyn_viol(_max), act_viol, lam/nu mean and
    max, plan_reward, plan_value, plan_return, shadow_reward, shadow_return, feasible,
    iters_to_feasible, nonfinite (all scalars).
    """
    new, metrics, _ = _replan(planner, params, ctx, state, key, None)
    return new, metrics


def shadow_batch(model: LatentModel, params: Any, ctx: Any, actions: jax.Array) -> dict:
    """Feasible rollout of the clipped plan actions as a one-sequence value batch (§4.3).

    actions: [H, A]. Returns feat [1, T, F], reward [1, T], is_first [1, T] with T = H + 1 when the
    model has ``ctx_feat`` (the start state leads, its reward slot is unused) and T = H otherwise.
    """
    z = rollout(model, params, ctx, jnp.clip(actions, -1.0, 1.0))
    feat = jax.vmap(model.feat, in_axes=(None, 0))(params, z)
    rew = jax.vmap(model.reward, in_axes=(None, 0))(params, z)
    if model.ctx_feat is not None:
        feat = jnp.concatenate([model.ctx_feat(params, ctx)[None], feat], axis=0)
        rew = jnp.concatenate([jnp.zeros((1,), rew.dtype), rew], axis=0)
    return {
        "feat": jax.lax.stop_gradient(feat)[None],
        "reward": jax.lax.stop_gradient(rew)[None],
        "is_first": jnp.zeros((1, rew.shape[0]), bool),
    }


def plan_value_batch(model: LatentModel, params: Any, ctx: Any, actions: jax.Array) -> dict:
    """``plan_final`` value batch over envs: shadow rollouts of each env's final plan.

    ctx: contexts with a leading env axis [E, ...]; actions: [E, H, A] (e.g. ``planner.actions``
    of the returned plans). Returns feat [E, T, F], reward and is_first [E, T] for
    :func:`mjx_collo.value.train_step`.
    """
    batch = jax.vmap(shadow_batch, in_axes=(None, None, 0, 0))(model, params, ctx, actions)
    return jax.tree.map(lambda x: x[:, 0], batch)


def replan_value(
    planner: Planner,
    model: LatentModel,
    params: Any,
    ctx: Any,
    state: MPCState,
    vstate: value_lib.ValueState,
    key: jax.Array,
    axis_name: str | None = None,
) -> tuple[MPCState, Metrics, value_lib.ValueState]:
    """:func:`replan` with ``plan_inner`` value learning (Algorithm 1 made sound, §4.3).

    Every ``value.v_every`` solver iterations the online value takes one step on the shadow rollout
    of the current plan's clipped actions; the bootstrap inside the plan keeps using the frozen
    target carried in ``params``. Inside a vmap over envs pass that axis as ``axis_name`` so the
    gradients are averaged and all envs hold the same value state.
    """
    cfg = planner.cfg
    if model.feat is None:
        raise ValueError("plan_inner value learning needs model.feat")

    def step(carry, plan: PlanState, k: jax.Array):
        vs, _ = carry
        batch = shadow_batch(model, params, ctx, plan.a)
        vs, m = value_lib.train_step(cfg.value, vs, batch, k, axis_name)
        return vs, m["value/loss"]

    inner = (cfg.value.v_every, step, (vstate, jnp.zeros((), jnp.float32)))
    new, metrics, (vstate, loss) = _replan(planner, params, ctx, state, key, inner)
    return new, {**metrics, "value/plan_loss": loss}, vstate


def next_action(
    cfg: Config, state: MPCState, key: jax.Array, training: bool, eps: jax.Array | None = None
) -> tuple[jax.Array, MPCState]:
    """Pop the next cached action; add ``explore.noise`` x unit noise in training; clip to [-1, 1].

    The unit noise is ``eps`` [A] where given (colored over the episode, see
    :func:`mjx_collo.agent.explore_eps`), else white N(0, 1) from ``key``.
    Returns (action [A], state with pos + 1). Past the end of the cache the last action repeats
    (the trainer replans every ``cache_len`` steps, so this only happens if it does not).
    """
    m = state.actions.shape[0]
    a = state.actions[jnp.clip(state.pos, 0, m - 1)]
    if training:
        if eps is None:
            eps = jax.random.normal(key, a.shape, a.dtype)
        a = a + cfg.explore.noise * eps
    return jnp.clip(a, -1.0, 1.0), state.replace(pos=state.pos + 1)

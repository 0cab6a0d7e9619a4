"""The latent-model protocol the planners are written against, and rollouts through it.

A :class:`LatentModel` is a NamedTuple of pure, *unbatched* functions; callers vmap over envs and
seeds. The world model's is built by :func:`mjx_collo.world_model.latent_model`; tests also write
small analytic ones. ``params`` is an opaque pytree (world-model params, plus target-value params when the model
bootstraps). Plan-space states ``z`` are flat vectors ``[Z]``; what they mean (full ``[stoch, deter]``
or reduced ``deter``) is the world model's business.

Conventions (docs/ALGORITHM.md §4.1, pitfall 7):
  * ``reward(params, z)`` is the reward received on *arriving* in ``z``;
  * ``value(params, z)`` is the discounted value of ``z`` *excluding* its own reward, so the planner
    maximises ``J = sum_{k=1..H} gamma^(k-1) r(z_k) + gamma^H V(z_H)``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

Params = Any
Context = Any


class LatentModel(NamedTuple):
    """Pure, unbatched latent-model functions (the planner's only view of the world model).

    Attributes:
      start: ``(params, ctx, a [A]) -> z1 [Z]`` deterministic transition out of the filtered
        posterior context ``ctx`` (any pytree) under the first action.
      step: ``(params, z [Z], a [A]) -> z' [Z]`` deterministic transition between plan states.
      reward: ``(params, z [Z]) -> []`` reward of arriving in ``z``.
      value: ``(params, z [Z]) -> []`` frozen (target) value of ``z`` excluding its own reward, or
        None when the model has no value.
      feat: ``(params, z [Z]) -> [F]`` value-network input features of ``z`` (needed only by the
        plan-based value-learning modes), or None.
      ctx_feat: ``(params, ctx) -> [F]`` features of the context (the plan's start state), or None.
      step_reward: optional ``(params, z [Z], a [A]) -> (step(z, a), reward(z))`` in one pass, for
        models where the two share work (the reduced RSSM space computes the prior of ``z`` for
        both); equal to calling ``step`` and ``reward``. None: the planners call them separately.
      step_reward_value: optional ``(params, z, a) -> (step(z, a), reward(z), value(z))`` in one
        pass (the value read off the same features), for objectives that read V at every plan
        state (``planner.value_lambda < 1``). None: ``value`` is called separately.
      step_feat: optional ``(params, z, a) -> (step(z, a), feat(z))`` in one pass, with
        ``feat_reward`` ``(params, f [F]) -> []`` (and ``feat_value``, the value of a feature, for
        models with a value): rollouts then scan only the transitions and read the reward (and
        value) heads of all H states afterwards in one batched call, instead of H small calls
        inside the sequential loop (the heads are half of a rollout's FLOPs). None: the heads
        run inside the loop (``step_reward`` / ``step_reward_value``).
      policy: optional ``(params, z [Z]) -> a [A]`` the policy prior's action at plan state ``z``
        (``planner.init: policy``), with ``ctx_policy`` ``(params, ctx) -> a_0`` at the context;
        :func:`policy_rollout` runs it through the model to start a plan. None: no prior.
    """

    start: Callable[[Params, Context, jax.Array], jax.Array]
    step: Callable[[Params, jax.Array, jax.Array], jax.Array]
    reward: Callable[[Params, jax.Array], jax.Array]
    value: Callable[[Params, jax.Array], jax.Array] | None = None
    feat: Callable[[Params, jax.Array], jax.Array] | None = None
    ctx_feat: Callable[[Params, Context], jax.Array] | None = None
    step_reward: Callable[[Params, jax.Array, jax.Array], tuple[jax.Array, jax.Array]] | None = None
    step_reward_value: (
        Callable[[Params, jax.Array, jax.Array], tuple[jax.Array, jax.Array, jax.Array]] | None
    ) = None
    step_feat: Callable[[Params, jax.Array, jax.Array], tuple[jax.Array, jax.Array]] | None = None
    feat_reward: Callable[[Params, jax.Array], jax.Array] | None = None
    feat_value: Callable[[Params, jax.Array], jax.Array] | None = None
    policy: Callable[[Params, jax.Array], jax.Array] | None = None
    ctx_policy: Callable[[Params, Context], jax.Array] | None = None


def latent_size(model: LatentModel, params: Params, ctx: Context, action_dim: int) -> int:
    """Size Z of the plan-space state (by abstract evaluation; no FLOPs)."""
    a = jax.ShapeDtypeStruct((action_dim,), jnp.float32)
    out = jax.eval_shape(model.start, params, ctx, a)
    return int(out.shape[-1])


def _scan_states(
    model: LatentModel, params: Params, ctx: Context, actions: jax.Array, step_out: Callable
) -> tuple[jax.Array, Any, jax.Array]:
    """The one rollout loop: z_1 = start(ctx, a_0), then ``step_out(params, z_t, a_t) ->
    (z_{t+1}, out_t)`` for t = 1..H-1. Returns (z [H, Z], the outs of z_1..z_{H-1} stacked,
    z_H)."""
    z1 = model.start(params, ctx, actions[0])

    def body(z: jax.Array, a: jax.Array) -> tuple[jax.Array, tuple[jax.Array, Any]]:
        nz, out = step_out(params, z, a)
        return nz, (nz, out)

    z_last, (rest, outs) = jax.lax.scan(body, z1, actions[1:])
    return jnp.concatenate([z1[None], rest], axis=0), outs, z_last


def rollout(model: LatentModel, params: Params, ctx: Context, actions: jax.Array) -> jax.Array:
    """Feasible latent trajectory under ``actions``.

    Args:
      actions: [H, A] actions a_0..a_{H-1}.
    Returns:
      z: [H, Z] states z_1..z_H (z_1 = start(ctx, a_0), z_{t+1} = step(z_t, a_t)).
    """
    z, _, _ = _scan_states(model, params, ctx, actions, lambda p, z, a: (model.step(p, z, a), ()))
    return z


def policy_rollout(
    model: LatentModel, params: Params, ctx: Context, horizon: int
) -> tuple[jax.Array, jax.Array]:
    """The policy prior run through the model from ``ctx``: a feasible plan (z [H, Z] states
    z_1..z_H, a [H, A] actions a_0..a_{H-1}) with a_0 = ctx_policy(ctx), z_1 = start(ctx, a_0),
    a_k = policy(z_k), z_{k+1} = step(z_k, a_k)."""
    if model.policy is None or model.ctx_policy is None:
        raise ValueError("policy_rollout needs a model with a policy prior (policy, ctx_policy)")
    a0 = model.ctx_policy(params, ctx)
    z1 = model.start(params, ctx, a0)

    def body(z: jax.Array, _) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
        a = model.policy(params, z)
        nz = model.step(params, z, a)
        return nz, (a, nz)

    _, (a_rest, z_rest) = jax.lax.scan(body, z1, None, length=horizon - 1)
    return jnp.concatenate([z1[None], z_rest], 0), jnp.concatenate([a0[None], a_rest], 0)


def _batched_heads(model: LatentModel, value: bool) -> bool:
    """Whether rollouts can read the heads after the loop (see ``LatentModel.step_feat``)."""
    ok = None not in (model.step_feat, model.feat_reward, model.feat)
    return ok and (model.feat_value is not None or not value)


def rollout_feats(
    model: LatentModel, params: Params, ctx: Context, actions: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """:func:`rollout` and the features of its states: z [H, Z], feat(z_k) [H, F]. The loop
    carries only the transitions (``step_feat``: each state's features come out of the pass that
    steps it); the last state's features are computed after the loop."""
    z, f_head, z_last = _scan_states(model, params, ctx, actions, model.step_feat)
    return z, jnp.concatenate([f_head, model.feat(params, z_last)[None]], axis=0)


def rollout_rewards(
    model: LatentModel, params: Params, ctx: Context, actions: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """:func:`rollout` and the rewards r(z_k) [H] of its states in one pass: with the model's
    ``step_reward`` each state's shared work (the reduced RSSM space: its prior) is done once
    for its transition and its reward, instead of once in the rollout and again for the reward;
    with ``step_feat`` and ``feat_reward`` the rewards are read after the loop, batched."""
    if _batched_heads(model, value=False):
        z, f = rollout_feats(model, params, ctx, actions)
        return z, jax.vmap(model.feat_reward, in_axes=(None, 0))(params, f)
    if model.step_reward is None:
        z = rollout(model, params, ctx, actions)
        return z, jax.vmap(model.reward, in_axes=(None, 0))(params, z)
    z, r_head, z_last = _scan_states(model, params, ctx, actions, model.step_reward)
    return z, jnp.concatenate([r_head, model.reward(params, z_last)[None]], axis=0)


def rollout_rewards_values(
    model: LatentModel, params: Params, ctx: Context, actions: jax.Array
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """:func:`rollout` with the rewards and (unclipped) values of its states [H]: with the
    model's ``step_reward_value`` each state's features are computed once for its transition,
    reward and value (with ``step_feat``, ``feat_reward`` and ``feat_value``: the features in the
    loop, both heads after it, batched over the H states)."""
    if _batched_heads(model, value=True):
        z, f = rollout_feats(model, params, ctx, actions)
        r = jax.vmap(model.feat_reward, in_axes=(None, 0))(params, f)
        return z, r, jax.vmap(model.feat_value, in_axes=(None, 0))(params, f)
    if model.step_reward_value is None:
        z, r = rollout_rewards(model, params, ctx, actions)
        return z, r, jax.vmap(model.value, in_axes=(None, 0))(params, z)

    def step_out(p: Params, z: jax.Array, a: jax.Array) -> tuple[jax.Array, tuple]:
        nz, r, v = model.step_reward_value(p, z, a)
        return nz, (r, v)

    z, (r_head, v_head), z_last = _scan_states(model, params, ctx, actions, step_out)
    r_last, v_last = last_reward_value(model, params, z_last, actions[0])
    return z, jnp.append(r_head, r_last), jnp.append(v_head, v_last)


def last_reward_value(
    model: LatentModel, params: Params, z: jax.Array, a_like: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """(reward(z), value(z)) of the plan's last state through ``step_reward_value``; its
    transition (under a zero action shaped like ``a_like``) is unused, so XLA drops it."""
    _, r, v = model.step_reward_value(params, z, jnp.zeros_like(a_like))
    return r, v


def discounts(gamma: jax.Array | float, horizon: int) -> jax.Array:
    """[H] weights gamma^(k-1) of the rewards r(z_k), k = 1..H."""
    return jnp.power(jnp.asarray(gamma, jnp.float32), jnp.arange(horizon, dtype=jnp.float32))


def lambda_return(
    rewards: jax.Array, values: jax.Array, gamma: jax.Array | float, lam: jax.Array | float
) -> jax.Array:
    """Dreamer's lambda-return of a plan from its start: ``G_H = V(z_H)``,
    ``G_k = r_{k+1} + gamma ((1 - lam) V(z_{k+1}) + lam G_{k+1})``; returns ``G_0``.

    rewards, values: [H], r(z_k) and V(z_k) for k = 1..H. ``lam = 1`` is
    ``sum_k gamma^(k-1) r_k + gamma^H V(z_H)``; smaller ``lam`` leans on the value of the states
    near the start, where it was trained, rather than only on the plan's far end.
    """

    def body(g, x):
        r, v = x
        return r + gamma * ((1.0 - lam) * v + lam * g), None

    g, _ = jax.lax.scan(body, values[-1], (rewards, values), reverse=True)
    return g


def discounted_return(
    rewards: jax.Array, last_value: jax.Array, gamma: jax.Array | float, bootstrap: bool
) -> jax.Array:
    """``sum_k gamma^(k-1) r_k (+ gamma^H V(z_H))``; rewards: [H]; last_value: []."""
    h = rewards.shape[0]
    ret = jnp.sum(discounts(gamma, h) * rewards)
    if bootstrap:
        ret = ret + jnp.power(jnp.asarray(gamma, jnp.float32), h) * last_value
    return ret

"""The collocation problem: residuals, weights and the exact objective (docs/ALGORITHM.md §3.2, §4.1).

Decision variables are ``z`` [H, Z] (z_1..z_H) and ``a`` [H, A] (a_0..a_{H-1}); the context x_0 is
fixed exactly. Residual rows, each scaled by LC's kappa:

* dynamics   ``sqrt(lam_t) s_d d_t``, d_0 = z_1 - start(ctx, a_0), d_t = z_{t+1} - step(z_t, a_t);
* bounds     ``sqrt(nu_t) s_a max(|a_t| - 1, 0)``;
* reward     ``gamma^((k-1)/2) softplus(-r(z_k))``, k = 1..H (gamma = 1 recovers LatCo);
* value      ``s_V softplus(-(1 - gamma) clip(V(z_H)))``, s_V = sqrt(gamma^H / (1 - gamma)) when
  ``value.residual_scale`` is ``auto``, so that dC/dV matches gamma^H dC/dr (ColloDreamer only).

The exact objective (for the ``adam`` primal and for reporting) is
``J = sum_k gamma^(k-1) r(z_k) + gamma^H clip(V(z_H))`` (with ``planner.value_lambda < 1``: the
lambda-return of the plan, which reads V at every plan state) and the Lagrangian
``-J + sum_t lam_t s_d^2 ||d_t||^2 + sum_t nu_t s_a^2 ||max(|a_t|-1, 0)||^2``.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from mjx_collo.config import Config
from mjx_collo.planners import duals
from mjx_collo.planners.protocol import (
    LatentModel,
    discounted_return,
    discounts,
    lambda_return,
    last_reward_value,
    rollout_rewards,
    rollout_rewards_values,
)


class Problem(NamedTuple):
    """One planning problem: model, its params, the fixed context and the objective constants.

    Float fields may be JAX tracers (swept hyperparameters); ``bootstrap``, ``clip`` and
    ``lambda_values`` are static. ``lambda_values``: the objective is the lambda-return with
    ``value_lambda`` (V at every plan state) instead of the end bootstrap.
    """

    model: LatentModel
    params: Any
    ctx: Any
    gamma: Any
    bootstrap: bool
    value_scale: Any
    clip: bool
    value_lo: Any
    value_hi: Any
    dyn_scale: Any
    act_scale: Any
    value_lambda: Any = 1.0
    lambda_values: bool = False


class Raw(NamedTuple):
    """Unweighted residual blocks. d: [H, Z]; hinge: [H, A]; rew: [H]; val: []."""

    d: jax.Array
    hinge: jax.Array
    rew: jax.Array
    val: jax.Array


class Weights(NamedTuple):
    """Row weights of the residual vector. dyn, act, rew: [H]; val: [] (0 without bootstrap)."""

    dyn: jax.Array
    act: jax.Array
    rew: jax.Array
    val: jax.Array


def make_problem(cfg: Config, model: LatentModel, params: Any, ctx: Any) -> Problem:
    """Collect the objective constants of ``cfg`` (ColloDreamer bootstraps, LatCo does not)."""
    pc, vc = cfg.planner, cfg.value
    bootstrap = pc.kind in ("collodreamer", "mppi_value") and vc.bootstrap
    if bootstrap and model.value is None:
        raise ValueError(f"planner.kind={pc.kind} with value.bootstrap needs model.value")
    gamma = jnp.asarray(pc.gamma, jnp.float32)
    if vc.residual_scale == "auto":
        one_minus = jnp.maximum(1.0 - gamma, 1e-6)
        scale = jnp.sqrt(jnp.power(gamma, pc.horizon) / one_minus)
    else:
        scale = jnp.asarray(vc.residual_scale, jnp.float32)
    lam = pc.value_lambda
    lambda_values = bootstrap and not (isinstance(lam, float) and lam == 1.0)
    if lambda_values and pc.kind in ("latco", "collodreamer") and pc.solver != "adam":
        raise ValueError(
            f"planner.value_lambda={lam} needs planner.solver=adam: the Gauss-Newton residuals "
            "bootstrap the value at the plan's end only (use value_lambda=1.0 with "
            f"solver={pc.solver})"
        )
    return Problem(
        model=model,
        params=params,
        ctx=ctx,
        gamma=gamma,
        bootstrap=bootstrap,
        value_scale=scale,
        clip=vc.clip,
        value_lo=vc.clip_range[0],
        value_hi=vc.clip_range[1],
        dyn_scale=pc.dyn_scale,
        act_scale=pc.act_scale,
        value_lambda=lam,
        lambda_values=lambda_values,
    )


def predict(prob: Problem, z: jax.Array, a: jax.Array) -> jax.Array:
    """Model prediction of every plan state from its predecessor. z: [H, Z], a: [H, A] -> [H, Z].

    All H transitions are independent given the plan, so they run as one batched call.
    """
    m, p = prob.model, prob.params
    z1 = m.start(p, prob.ctx, a[0])
    rest = jax.vmap(m.step, in_axes=(None, 0, 0))(p, z[:-1], a[1:])
    return jnp.concatenate([z1[None], rest], axis=0)


def predict_and_rewards(prob: Problem, z: jax.Array, a: jax.Array) -> tuple[jax.Array, jax.Array]:
    """:func:`predict` and the rewards r(z_k) [H] of the plan states, sharing the work the model's
    ``step_reward`` shares (the reduced RSSM space: one prior per state instead of two)."""
    m, p = prob.model, prob.params
    if m.step_reward is None:
        return predict(prob, z, a), jax.vmap(m.reward, in_axes=(None, 0))(p, z)
    z1 = m.start(p, prob.ctx, a[0])
    rest, r_head = jax.vmap(m.step_reward, in_axes=(None, 0, 0))(p, z[:-1], a[1:])
    r_last = m.reward(p, z[-1])
    pred = jnp.concatenate([z1[None], rest], axis=0)
    return pred, jnp.concatenate([r_head, r_last[None]], axis=0)


def predict_rewards_values(
    prob: Problem, z: jax.Array, a: jax.Array
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """:func:`predict_and_rewards` and the (unclipped) values V(z_k) [H] of the plan states, with
    the model's ``step_reward_value`` computing each state's features once for all three."""
    m, p = prob.model, prob.params
    if m.step_reward_value is None:
        pred, rewards = predict_and_rewards(prob, z, a)
        return pred, rewards, jax.vmap(m.value, in_axes=(None, 0))(p, z)
    z1 = m.start(p, prob.ctx, a[0])
    rest, r_head, v_head = jax.vmap(m.step_reward_value, in_axes=(None, 0, 0))(p, z[:-1], a[1:])
    r_last, v_last = last_reward_value(m, p, z[-1], a[0])
    pred = jnp.concatenate([z1[None], rest], axis=0)
    return pred, jnp.append(r_head, r_last), jnp.append(v_head, v_last)


def clip_value(prob: Problem, v: jax.Array) -> jax.Array:
    """Values as the objective reads them: clipped to ``value.clip_range`` when ``value.clip``."""
    return jnp.clip(v, prob.value_lo, prob.value_hi) if prob.clip else v


def bootstrap_value(prob: Problem, z_last: jax.Array) -> jax.Array:
    """Frozen value of the last plan state, clipped when ``value.clip``. z_last: [Z] -> []."""
    if not prob.bootstrap:
        return jnp.zeros((), z_last.dtype)
    return clip_value(prob, prob.model.value(prob.params, z_last))


def plan_return(
    prob: Problem, zs: jax.Array, rewards: jax.Array, values: jax.Array | None = None
) -> tuple[jax.Array, jax.Array]:
    """``(J, V(z_H))`` of plan states ``zs`` [H, Z] with rewards r(z_k) [H]: the discounted reward
    sum plus ``gamma^H V(z_H)``, or the lambda-return when ``prob.lambda_values`` (over
    ``values``, the unclipped V(z_k) [H] when the caller has them)."""
    if prob.lambda_values:
        if values is None:
            values = jax.vmap(prob.model.value, in_axes=(None, 0))(prob.params, zs)
        values = clip_value(prob, values)
        return lambda_return(rewards, values, prob.gamma, prob.value_lambda), values[-1]
    v = bootstrap_value(prob, zs[-1])
    return discounted_return(rewards, v, prob.gamma, prob.bootstrap), v


def rollout_return(
    prob: Problem, a: jax.Array
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """``(J, rewards [H], states [H, Z], V(z_H))`` of the feasible model rollout of actions ``a``
    [H, A]; the lambda-return reads each state's value in the rollout's own pass."""
    if prob.lambda_values:
        zs, rs, vs = rollout_rewards_values(prob.model, prob.params, prob.ctx, a)
    else:
        zs, rs = rollout_rewards(prob.model, prob.params, prob.ctx, a)
        vs = None
    j, v = plan_return(prob, zs, rs, vs)
    return j, rs, zs, v


def reward_residual(prob: Problem, z: jax.Array) -> jax.Array:
    """softplus(-r(z)). z: [Z] -> []."""
    return jax.nn.softplus(-prob.model.reward(prob.params, z))


def value_residual(prob: Problem, z_last: jax.Array) -> jax.Array:
    """softplus(-(1 - gamma) V(z_H)) (0 without bootstrap). z_last: [Z] -> []."""
    if not prob.bootstrap:
        return jnp.zeros((), z_last.dtype)
    return jax.nn.softplus(-(1.0 - prob.gamma) * bootstrap_value(prob, z_last))


def raw_residuals(prob: Problem, z: jax.Array, a: jax.Array) -> Raw:
    """Unweighted residual blocks of the plan. z: [H, Z], a: [H, A]."""
    pred, rewards = predict_and_rewards(prob, z, a)
    return Raw(
        d=z - pred,
        hinge=duals.act_hinge(a),
        rew=jax.nn.softplus(-rewards),
        val=value_residual(prob, z[-1]),
    )


def weights(prob: Problem, lam: jax.Array, nu: jax.Array) -> Weights:
    """Residual row weights for multipliers lam, nu: [H] (kappa-normalised, LC)."""
    k = duals.kappa(lam, nu, prob.dyn_scale, prob.act_scale)
    h = lam.shape[0]
    val = k * prob.value_scale if prob.bootstrap else jnp.zeros((), jnp.float32)
    return Weights(
        dyn=k * prob.dyn_scale * jnp.sqrt(lam),
        act=k * prob.act_scale * jnp.sqrt(nu),
        rew=k * jnp.sqrt(discounts(prob.gamma, h)),
        val=val,
    )


def weighted(raw: Raw, w: Weights) -> Raw:
    """Residual blocks multiplied by their row weights."""
    return Raw(
        d=w.dyn[:, None] * raw.d,
        hinge=w.act[:, None] * raw.hinge,
        rew=w.rew * raw.rew,
        val=w.val * raw.val,
    )


def cost(raw: Raw, w: Weights) -> jax.Array:
    """Gauss-Newton cost ||rho||^2 of the weighted residual."""
    r = weighted(raw, w)
    return sum(jnp.sum(jnp.square(x)) for x in r)


def exact_terms(prob: Problem, z: jax.Array, a: jax.Array) -> tuple[jax.Array, jax.Array, Raw]:
    """Exact objective pieces: (J [], rewards [H], raw residuals for the constraints)."""
    if prob.lambda_values:
        pred, rewards, values = predict_rewards_values(prob, z, a)
    else:
        (pred, rewards), values = predict_and_rewards(prob, z, a), None
    j, v = plan_return(prob, z, rewards, values)
    raw = Raw(d=z - pred, hinge=duals.act_hinge(a), rew=rewards, val=v)
    return j, rewards, raw


def lagrangian(
    prob: Problem, z: jax.Array, a: jax.Array, lam: jax.Array, nu: jax.Array
) -> tuple[jax.Array, Raw]:
    """Exact Lagrangian -J + sum lam s_d^2 ||d||^2 + sum nu s_a^2 ||hinge||^2, and raw terms."""
    j, _, raw = exact_terms(prob, z, a)
    dyn = jnp.sum(lam * jnp.square(prob.dyn_scale) * duals.dyn_violation(raw.d))
    act = jnp.sum(nu * jnp.square(prob.act_scale) * jnp.sum(jnp.square(raw.hinge), -1))
    return -j + dyn + act, raw

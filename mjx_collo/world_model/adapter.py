"""The world model as its consumers see it: the one latent-model adapter for the planners
(:class:`~mjx_collo.planners.protocol.LatentModel`) and the imagination protocol of the Dreamer
actor (:class:`~mjx_collo.actor.ImaginationModel`).

The trainer, the tests and the benchmarks all build their planning model here, so what is tested
and benchmarked is what trains.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from mjx_collo.actor import ImaginationModel
from mjx_collo.config import WorldModelConfig
from mjx_collo.planners.protocol import LatentModel
from mjx_collo.world_model.heads import reward
from mjx_collo.world_model.rssm import (
    RSSMState,
    _transition,
    get_feat,
    img_step,
    prior_mean,
    stoch_size,
)

Params = Any
ValueFn = Callable[[Params, jax.Array], jax.Array]


def plan_params(
    wm_params: Params, value_params: Params = None, policy_params: Params = None
) -> tuple[Params, ...]:
    """Params of the :func:`latent_model`: (world model, frozen target value or None), and the
    policy prior's params third when the planner starts from it (``planner.init: policy``)."""
    if policy_params is None:
        return (wm_params, value_params)
    return (wm_params, value_params, policy_params)


def latent_model(
    cfg: WorldModelConfig,
    space: str,
    value: ValueFn | None = None,
    policy: ValueFn | None = None,
) -> LatentModel:
    """The world model in plan space (docs/ALGORITHM.md §3.2, §4.2), with params
    :func:`plan_params` ``(wm_params, value_params)``.

    ``space``: ``full``: z = [m, h] with m the stoch mean (gaussian mean / flat categorical
    probabilities), step = LatCo's ``F_mu = get_mean_feat(img_step(from_feat(z), a))``
    (probabilities fed where samples would be). ``reduced``: z = h only, with ``s := m(h)``;
    exact at feasibility because the prior statistics are a function of h alone.

    ``value``: ``(value_params, f [F]) -> []``, the value the planner bootstraps with (already
    clipped as the planner should see it), or None for a model without a value.

    ``policy``: ``(policy_params, f [F]) -> a [A]``, the policy prior's deterministic action on
    features (params third in :func:`plan_params`), or None. In plan space it reads the features
    of the plan state (the stoch mean where the actor saw samples).

    The fused functions (``step_reward``, ``step_reward_value``, ``step_feat``) share one prior
    pass per state between its transition and its heads; rollouts read the reward and value heads
    of all plan states after the loop in one batched call (see ``LatentModel``).
    """
    s_dim = stoch_size(cfg)

    if space == "full":

        def start(p: Params, ctx: RSSMState, a: jax.Array) -> jax.Array:
            h = _transition(cfg, p, ctx.stoch, ctx.deter, a)
            return jnp.concatenate([prior_mean(cfg, p, h), h], -1)

        def step(p: Params, z: jax.Array, a: jax.Array) -> jax.Array:
            h = _transition(cfg, p, z[..., :s_dim], z[..., s_dim:], a)
            return jnp.concatenate([prior_mean(cfg, p, h), h], -1)

        def feat(p: Params, z: jax.Array) -> jax.Array:
            return z

        def step_feat(p: Params, z: jax.Array, a: jax.Array) -> tuple[jax.Array, jax.Array]:
            return step(p, z, a), z

    elif space == "reduced":

        def start(p: Params, ctx: RSSMState, a: jax.Array) -> jax.Array:
            return _transition(cfg, p, ctx.stoch, ctx.deter, a)

        def step(p: Params, z: jax.Array, a: jax.Array) -> jax.Array:
            return _transition(cfg, p, prior_mean(cfg, p, z), z, a)

        def feat(p: Params, z: jax.Array) -> jax.Array:
            return jnp.concatenate([prior_mean(cfg, p, z), z], -1)

        def step_feat(p: Params, z: jax.Array, a: jax.Array) -> tuple[jax.Array, jax.Array]:
            m = prior_mean(cfg, p, z)
            return _transition(cfg, p, m, z, a), jnp.concatenate([m, z], -1)

    else:
        raise ValueError(f"unknown collocation space {space!r}; valid: full, reduced")

    def feat_reward(p: Params, f: jax.Array) -> jax.Array:
        return reward(cfg, p, f)

    def step_reward_feat(p: Params, z: jax.Array, a: jax.Array):
        nz, f = step_feat(p, z, a)
        return nz, feat_reward(p, f), f

    def step_reward(p: Params, z: jax.Array, a: jax.Array) -> tuple[jax.Array, jax.Array]:
        nz, r, _ = step_reward_feat(p, z, a)
        return nz, r

    def step_reward_value(pp, z, a):
        nz, r, f = step_reward_feat(pp[0], z, a)
        return nz, r, value(pp[1], f)

    return LatentModel(
        start=lambda pp, ctx, a: start(pp[0], ctx, a),
        step=lambda pp, z, a: step(pp[0], z, a),
        reward=lambda pp, z: reward(cfg, pp[0], feat(pp[0], z)),
        value=None if value is None else (lambda pp, z: value(pp[1], feat(pp[0], z))),
        feat=lambda pp, z: feat(pp[0], z),
        ctx_feat=lambda pp, ctx: get_feat(ctx),
        step_reward=lambda pp, z, a: step_reward(pp[0], z, a),
        step_reward_value=None if value is None else step_reward_value,
        step_feat=lambda pp, z, a: step_feat(pp[0], z, a),
        feat_reward=lambda pp, f: feat_reward(pp[0], f),
        feat_value=None if value is None else (lambda pp, f: value(pp[1], f)),
        policy=None if policy is None else (lambda pp, z: policy(pp[2], feat(pp[0], z))),
        ctx_policy=None if policy is None else (lambda pp, ctx: policy(pp[2], get_feat(ctx))),
    )


def imagination_model(cfg: WorldModelConfig) -> ImaginationModel:
    """The world model as the Dreamer actor's stochastic imagination protocol."""
    return ImaginationModel(
        img_step=lambda p, s, a, k: img_step(cfg, p, s, a, k),
        get_feat=get_feat,
        reward=lambda p, f: reward(cfg, p, f),
    )

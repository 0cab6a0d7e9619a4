"""Acting: posterior filtering -> planner (MPC) or Dreamer actor -> exploration noise.

All functions act on a batch of ``E`` envs (the agent carry has a leading env axis) and are pure;
*when* to replan is decided by the caller from an unbatched schedule (see :mod:`mjx_collo.trainer`).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from mjx_collo import actor as actor_lib
from mjx_collo import config as config_lib
from mjx_collo import explorer as explorer_lib
from mjx_collo import planner as planner_lib
from mjx_collo import value as value_lib
from mjx_collo import world_model as wm_lib
from mjx_collo.config import Config
from mjx_collo.noise import colored_normal
from mjx_collo.planners.protocol import LatentModel


@struct.dataclass
class AgentCarry:
    """Per-env acting state (leading axis E).

    post: posterior RSSM state at the last observation; prev_action: [E, A] action executed last
    (fed to the next filter step); mpc: action caches (None for the Dreamer actor).
    """

    post: wm_lib.RSSMState
    prev_action: jax.Array
    mpc: Any


@struct.dataclass
class ColoredCarry(AgentCarry):
    """The carry with colored exploration (``explore.color`` > 0): ``noise`` [E, T, A] is this
    episode's unit-variance noise per env, colored over its T agent steps. A subclass, not a field
    that is None for white noise, so the checkpoints of white-noise runs keep their structure."""

    noise: jax.Array


def carry_noise(carry: AgentCarry) -> jax.Array | None:
    """This episode's colored exploration noise [E, T, A]; None for white noise."""
    return carry.noise if isinstance(carry, ColoredCarry) else None


class Agent(NamedTuple):
    """How a seed acts: its config (swept values applied), the world model as the planner's
    latent model, and the planner (both None for the Dreamer actor, which acts from its actor).
    ``explore_planner``: the same planner on the model whose reward adds the disagreement bonus
    (``explore.disag.heads`` > 0), which makes the training plans; None without one."""

    cfg: Config
    action_dim: int
    model: LatentModel | None
    planner: planner_lib.Planner | None
    explore_planner: planner_lib.Planner | None = None

    @property
    def uses_actor(self) -> bool:
        return self.cfg.planner.kind == "dreamer"

    @property
    def uses_prior(self) -> bool:
        return uses_prior(self.cfg)

    @property
    def cache_len(self) -> int:
        return 1 if self.uses_actor else planner_lib.cache_len(self.cfg)


def value_bootstrap(cfg: Config) -> bool:
    """Whether the planner reads the (target) value network: ColloDreamer and MPPI with a value."""
    return (
        cfg.planner.kind in ("collodreamer", "mppi_value")
        and cfg.value.enabled
        and cfg.value.bootstrap
    )


uses_prior = config_lib.uses_prior  # re-exported: the trainer's modules ask the agent


def make_agent(cfg: Config, action_dim: int) -> Agent:
    """The agent of ``cfg`` (which may hold traced swept values): the world model's latent model
    (:func:`mjx_collo.world_model.latent_model`), with the clipped target value when the planner
    bootstraps, and the planner over it."""
    if cfg.planner.kind == "dreamer":
        return Agent(cfg, action_dim, None, None)
    value = None
    if value_bootstrap(cfg):

        def value(vp, f):
            return value_lib.clip_value(cfg.value, value_lib.apply_value(cfg.value, vp, f))

    policy = None
    if uses_prior(cfg):

        def policy(ap, f):
            return actor_lib.mode(cfg.actor, ap, f, action_dim)

    model = wm_lib.latent_model(cfg.wm, cfg.planner.space, value, policy)
    planner = planner_lib.make_planner(cfg, model, action_dim)
    explore_planner = None
    if cfg.explore.disag.heads:
        dc = cfg.explore.disag
        curious = explorer_lib.exploring_model(model, dc, dc.scale)
        explore_planner = planner_lib.make_planner(cfg, curious, action_dim)
    return Agent(cfg, action_dim, model, planner, explore_planner)


def episode_noise(cfg: Config, num_envs: int, action_dim: int, key: jax.Array) -> jax.Array:
    """One episode's exploration noise per env, ``[E, T, A]``: unit variance per step, power
    spectrum ~ 1/f^``explore.color`` over the episode's T agent steps, independent across envs
    and action dimensions (pink noise, Eberhard et al. 2023: long pushes a white sequence of the
    same scale almost never makes)."""
    steps = cfg.env.episode_env_steps // cfg.env.action_repeat
    return colored_normal(key, (num_envs, steps, action_dim), cfg.explore.color)


def init_carry(agent: Agent, params: tuple[Any, Any], num_envs: int, key: jax.Array) -> AgentCarry:
    cfg = agent.cfg
    post = wm_lib.initial_state(cfg.wm, (num_envs,))
    mpc = None
    if agent.planner is not None:
        one = jax.tree.map(lambda x: x[0], post)
        mpc0 = planner_lib.mpc_init(agent.planner, params, one, key)
        mpc = jax.tree.map(lambda x: jnp.broadcast_to(x, (num_envs,) + x.shape), mpc0)
    prev = jnp.zeros((num_envs, agent.action_dim))
    if cfg.explore.color > 0:
        noise = episode_noise(cfg, num_envs, agent.action_dim, jax.random.fold_in(key, 1))
        return ColoredCarry(post=post, prev_action=prev, mpc=mpc, noise=noise)
    return AgentCarry(post=post, prev_action=prev, mpc=mpc)


def reset_carry(agent: Agent, carry: AgentCarry, key: jax.Array | None = None) -> AgentCarry:
    """Episode boundary: forget the posterior, the last action and the action caches; draw the
    next episode's colored exploration noise from ``key`` (needed only for a
    :class:`ColoredCarry`, i.e. ``explore.color`` > 0)."""
    zero = jax.tree.map(jnp.zeros_like, carry.post)
    mpc = None if carry.mpc is None else jax.vmap(planner_lib.mpc_reset)(carry.mpc)
    carry = carry.replace(post=zero, prev_action=jnp.zeros_like(carry.prev_action), mpc=mpc)
    if isinstance(carry, ColoredCarry):
        e, _, a = carry.noise.shape
        carry = carry.replace(noise=episode_noise(agent.cfg, e, a, key))
    return carry


def explore_eps(carry: AgentCarry, key: jax.Array, t: jax.Array | None) -> jax.Array:
    """Unit-variance exploration noise ``[E, A]`` for agent step ``t`` of the episode: this
    episode's colored sequence at ``t`` if the carry keeps one, else white from ``key``."""
    if isinstance(carry, ColoredCarry):
        return jax.lax.dynamic_index_in_dim(carry.noise, t, axis=1, keepdims=False)
    return jax.random.normal(key, carry.prev_action.shape)


def observe(
    agent: Agent,
    wm_params: Any,
    carry: AgentCarry,
    obs: jax.Array,
    is_first: jax.Array,
    key: jax.Array,
) -> AgentCarry:
    """Posterior filtering of the new observations ``obs [E, ...]`` (``is_first [E]``)."""
    post, _ = wm_lib.obs_step(
        agent.cfg.wm, wm_params, carry.post, carry.prev_action, obs, is_first, key
    )
    return carry.replace(post=post)


def _env_mean(metrics: dict[str, jax.Array]) -> dict[str, jax.Array]:
    return {k: jnp.mean(v) for k, v in metrics.items()}


def replan(
    agent: Agent,
    params: tuple[Any, Any],
    carry: AgentCarry,
    key: jax.Array,
    planner: planner_lib.Planner | None = None,
) -> tuple[AgentCarry, dict[str, jax.Array]]:
    """One planning call per env from its posterior; metrics averaged over envs. ``planner``:
    another planner of the agent's (its ``explore_planner``, with its params) instead of its own."""
    keys = jax.random.split(key, carry.prev_action.shape[0])
    mpc, metrics = jax.vmap(planner_lib.replan, in_axes=(None, None, 0, 0, 0))(
        agent.planner if planner is None else planner, params, carry.post, carry.mpc, keys
    )
    return carry.replace(mpc=mpc), _env_mean(metrics)


def replan_inner(
    agent: Agent,
    params: tuple[Any, Any],
    carry: AgentCarry,
    vstate: value_lib.ValueState,
    key: jax.Array,
) -> tuple[AgentCarry, dict[str, jax.Array], value_lib.ValueState]:
    """``plan_inner`` value learning: value steps inside the planning loop, gradients averaged
    over envs so every env ends with the same value state."""
    keys = jax.random.split(key, carry.prev_action.shape[0])

    def one(ctx, mpc, k):
        return planner_lib.replan_value(
            agent.planner, agent.model, params, ctx, mpc, vstate, k, axis_name="envs"
        )

    mpc, metrics, vs = jax.vmap(one, axis_name="envs")(carry.post, carry.mpc, keys)
    return carry.replace(mpc=mpc), _env_mean(metrics), jax.tree.map(lambda x: x[0], vs)


def act(
    agent: Agent,
    params: Any,
    carry: AgentCarry,
    key: jax.Array,
    training: bool,
    t: jax.Array | None = None,
) -> tuple[jax.Array, AgentCarry]:
    """Actions ``[E, A]`` in [-1, 1] (the planner's with exploration noise in training only);
    records them as ``prev_action``. ``t``: the agent step within the episode, which indexes
    colored exploration noise (needed in training when ``explore.color`` > 0).

    ``params``: the actor variables for the Dreamer actor, else unused (actions come from caches).
    The Dreamer actor samples its own distribution here; its added exploration noise is the
    caller's (:func:`explore_eps`).
    """
    cfg = agent.cfg
    keys = jax.random.split(key, carry.prev_action.shape[0])
    if agent.uses_actor:
        feat = wm_lib.get_feat(carry.post)
        a = jax.vmap(lambda f, k: actor_lib.act(cfg.actor, params, f, k, training))(feat, keys)
        a = jnp.clip(a, -1.0, 1.0)
        return a, carry.replace(prev_action=a)
    # white noise stays drawn per env inside next_action, from the same keys as before colored
    # noise existed: runs and checkpoints of white-noise configs are bit-for-bit what they were
    if training and isinstance(carry, ColoredCarry):
        eps = explore_eps(carry, key, t)
        a, mpc = jax.vmap(lambda m, k, e: planner_lib.next_action(cfg, m, k, training, e))(
            carry.mpc, keys, eps
        )
    else:
        a, mpc = jax.vmap(lambda m, k: planner_lib.next_action(cfg, m, k, training))(
            carry.mpc, keys
        )
    return a, carry.replace(mpc=mpc, prev_action=a)

"""Learning: world-model updates on replay batches (with J_latent when enabled), and the value
(``value.mode=replay``) or the Dreamer actor-critic trained from each update's posteriors; the
value step on a plan's targets (``value.mode=plan_final``), which acting hands over in a
:class:`PlanTargets` right after the planning call; J_latent's weight from the planner's
multipliers.

``value.mode=plan_inner`` trains the value inside the planning loop itself
(:func:`mjx_collo.planner.replan_value`), so it happens while acting, not here.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from mjx_collo import actor as actor_lib
from mjx_collo import agent as agent_lib
from mjx_collo import explorer as explorer_lib
from mjx_collo import replay as replay_lib
from mjx_collo import value as value_lib
from mjx_collo import world_model as wm_lib
from mjx_collo.agent import Agent
from mjx_collo.config import Config
from mjx_collo.train_state import TrainState

Metrics = dict[str, jax.Array]
Bind = Callable[[dict[str, jax.Array]], tuple[Config, Agent]]


@struct.dataclass
class PlanTargets:
    """``value.mode=plan_final``'s value targets from one planning call: shadow rollouts of every
    env's final plan (``feat [E, T, F]``, ``reward``, ``is_first [E, T]``) and that call's key."""

    value_batch: dict[str, jax.Array]
    key: jax.Array


ValueOnPlan = Callable[[Config, value_lib.ValueState, PlanTargets], tuple[Any, Metrics]]


class Learner(NamedTuple):
    """Pure functions of one seed (see :func:`make_learner`)."""

    init: Callable[..., tuple[Any, Any, Any, Any, Any]]
    init_explorer: Callable[[Config, jax.Array], Any]
    update: Callable[[TrainState, jax.Array], tuple[TrainState, Metrics]]
    learn: Callable[[TrainState, jax.Array, jax.Array], tuple[TrainState, Metrics]]
    value_on_plan: ValueOnPlan
    track_multipliers: Callable[[TrainState, jax.Array], TrainState]


def make_learner(cfg: Config, obs_shape: tuple[int, ...], action_dim: int, bind: Bind) -> Learner:
    """Learning for ``cfg``; ``bind(hyper) -> (config with the swept values, Agent)``."""
    uses_actor = cfg.planner.kind == "dreamer"
    uses_prior = agent_lib.uses_prior(cfg)  # an actor trained as the planner's policy prior
    use_value = cfg.value.enabled
    value_mode = cfg.value.mode if use_value and not uses_actor else "none"
    feat_dim = wm_lib.feat_size(cfg.wm)

    def init(c: Config, k_wm: jax.Array, k_val: jax.Array, k_act: jax.Array):
        """-> (world model, its optimizer state, value state, actor state, J_latent's old model)."""
        wm = wm_lib.init(c.wm, k_wm, obs_shape, action_dim)
        vstate = value_lib.init_value(c.value, k_val, feat_dim) if use_value else None
        astate = (
            actor_lib.init_actor(c.actor, k_act, feat_dim, action_dim)
            if uses_actor or uses_prior
            else None
        )
        wm_old = wm if c.j_latent.enabled else None
        return wm, wm_lib.init_opt_state(c.wm, wm), vstate, astate, wm_old

    def init_explorer(c: Config, k_wm: jax.Array):
        """The disagreement ensemble (None without one), its key folded out of the world
        model's so every other key of a run stays what it was."""
        if not cfg.explore.disag.heads:
            return None
        (obs_dim,) = obs_shape  # config_lib.check_explore: state vectors only
        key = jax.random.fold_in(k_wm, 0x0E4D)
        return explorer_lib.init(c.explore.disag, key, feat_dim, obs_dim)

    def _update(s: TrainState, key: jax.Array) -> tuple[TrainState, Metrics]:
        """One world-model update (+ value on replay posteriors, or actor-critic)."""
        c, _ = bind(s.hyper)
        k_batch, k_wm, k_v = jax.random.split(key, 3)
        batch = replay_lib.sample(s.replay, k_batch, c.replay.batch, c.replay.length)
        jlat = None
        if c.j_latent.enabled:
            # beta_lat = beta0 / lambda_bar: the weight falls as the planner's dynamics
            # multipliers grow (docs/ALGORITHM.md §4.5); lambda_bar is an EMA of the plan mean.
            target = s.value.target
            jlat = wm_lib.JLatentArgs(
                old_params=s.wm_old,
                value_fn=lambda f: value_lib.apply_value(c.value, target, f),
                beta=c.j_latent.beta0 / jnp.maximum(s.lam_ema, 1.0),
                gamma=c.value.gamma,
                cfg=c.j_latent,
            )
        wm, wm_opt, wm_m, post = wm_lib.train_step(c.wm, s.wm, s.wm_opt, batch, k_wm, jlat)
        metrics = {f"wm/{k}": v for k, v in wm_m.items()}
        vstate, astate = s.value, s.actor
        if uses_actor:
            starts = actor_lib.flatten_starts(post.state, 2)
            imag = wm_lib.imagination_model(c.wm)
            astate, vstate, am = actor_lib.train_step(c, imag, wm, astate, vstate, starts, k_v)
            metrics.update(am)
        elif value_mode == "replay":
            vbatch = {"feat": post.feat, "reward": post.reward, "is_first": post.is_first}
            vstate, vm = value_lib.train_step(c.value, vstate, vbatch, k_v)
            metrics.update(vm)
        if uses_prior:
            # Dreamer's actor objective through the model, on the planner's own value (its target
            # params; weight actor.pg), and behaviour cloning of the planner's actions (actor.bc);
            # the value keeps learning its own way (value.mode)
            starts = actor_lib.flatten_starts(post.state, 2)
            k_a = jax.random.fold_in(k_v, 1)
            if 0 < cfg.actor.starts < cfg.replay.batch * cfg.replay.length:
                # a random subset of the posteriors starts the imagination: its cost is the
                # update's largest part (all 800: ~9x the world-model update's FLOPs)
                pick = jax.random.permutation(
                    jax.random.fold_in(k_a, 1), jax.tree.leaves(starts)[0].shape[0]
                )[: cfg.actor.starts]
                starts = jax.tree.map(lambda x: x[pick], starts)
            imag = wm_lib.imagination_model(c.wm)
            # behaviour cloning pairs: the posterior at t and the action taken from it (stored
            # with the next row), unless an episode starts there
            feat = jax.lax.stop_gradient(post.feat[:, :-1])
            bc = (
                feat.reshape(-1, feat.shape[-1]),
                batch["action"][:, 1:].reshape(-1, batch["action"].shape[-1]),
                (~batch["is_first"][:, 1:]).reshape(-1).astype(jnp.float32),
            )
            # the weights are (1, 0) unless set or swept: then skip the cloning term's cost
            # (~10% of the prior's update; forward only, as a metric); 1 x loss + 0 x clone is the same
            # update bit for bit
            weighted = (
                cfg.actor.pg != 1.0
                or cfg.actor.bc != 0.0
                or bool({"actor.pg", "actor.bc"} & set(s.hyper))
            )
            astate, _, am = actor_lib.actor_step(
                c, imag, wm, astate, vstate.target, starts, k_a, bc=bc if weighted else None
            )
            if not weighted:  # still report how far the planner's actions are from the prior's
                am["actor/loss_bc"] = actor_lib.bc_loss(c.actor, astate.params, *bc)
            metrics.update(am)
        explorer = s.explorer
        if explorer is not None:
            # the heads learn to predict step t+1's observation from step t's posterior features
            target = wm_lib.preprocess_obs(c.wm, wm, batch["obs"][:, 1:])
            feat = post.feat[:, :-1]
            mask = (~batch["is_first"][:, 1:]).astype(jnp.float32)
            explorer, em = explorer_lib.train_step(
                c.explore.disag,
                explorer,
                feat.reshape(-1, feat.shape[-1]),
                target.reshape(-1, target.shape[-1]),
                mask.reshape(-1),
            )
            metrics.update(em)
        bad = wm_m["nonfinite"] > 0
        streak = jnp.where(bad, s.nonfinite_streak + 1, 0)
        wm_old = s.wm_old
        if c.j_latent.enabled:
            refresh = (s.updates + 1) % c.j_latent.old_every == 0
            wm_old = jax.tree.map(lambda n, o: jnp.where(refresh, n, o), wm, s.wm_old)
        s = s.replace(
            wm=wm,
            wm_opt=wm_opt,
            value=vstate,
            actor=astate,
            wm_old=wm_old,
            explorer=explorer,
            updates=s.updates + 1,
            nonfinite_streak=streak,
            nonfinite_total=s.nonfinite_total + bad.astype(jnp.int32),
        )
        return s, metrics

    def _learn(s: TrainState, key: jax.Array, n: jax.Array) -> tuple[TrainState, Metrics]:
        """``n`` (unbatched) updates; metrics are means over them."""
        shapes = jax.eval_shape(_update, s, key)[1]
        zeros = {k: jnp.zeros(v.shape, jnp.float32) for k, v in shapes.items()}

        def body(i, carry):
            s, sums = carry
            s, m = _update(s, jax.random.fold_in(key, i))
            return s, {k: sums[k] + m[k].astype(jnp.float32) for k in sums}

        s, sums = jax.lax.fori_loop(0, n, body, (s, zeros))
        return s, {k: v / jnp.maximum(n, 1).astype(jnp.float32) for k, v in sums.items()}

    # Traced several times per program (output shapes, both branches of a lax.cond, FLOP
    # counts); as jitted functions with one identity the later traces come from JAX's cache.
    # XLA inlines them, so the compiled program is the same.
    _update = jax.jit(_update)
    _learn = jax.jit(_learn)

    def value_on_plan(c: Config, vstate: value_lib.ValueState, plan: PlanTargets):
        """One value step on a plan's targets (``value.mode=plan_final``)."""
        vstate, vm = value_lib.train_step(c.value, vstate, plan.value_batch, plan.key)
        return vstate, {f"plan_{k}": v for k, v in vm.items()}

    def track_multipliers(s: TrainState, lam_mean: jax.Array) -> TrainState:
        """EMA of the planner's mean dynamics multiplier (NaN: no plan this step), which sets
        J_latent's weight ``beta0 / max(lam_ema, 1)``."""
        finite = jnp.isfinite(lam_mean)
        return s.replace(lam_ema=jnp.where(finite, 0.99 * s.lam_ema + 0.01 * lam_mean, s.lam_ema))

    return Learner(
        init=init,
        init_explorer=init_explorer,
        update=_update,
        learn=_learn,
        value_on_plan=value_on_plan,
        track_multipliers=track_multipliers,
    )

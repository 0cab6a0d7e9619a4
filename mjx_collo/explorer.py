"""Curiosity for the planners: Plan2Explore's ensemble disagreement (Sekar et al. 2020).

An ensemble of ``explore.disag.heads`` small MLPs learns, from replay, to predict the next
observation from the world model's features. Where the model has seen enough data the heads
agree; where it has not (a body rolled onto a side it never reached) they disagree. In training,
the planner's reward adds ``explore.disag.scale`` x that disagreement, so plans seek what the model
cannot yet predict; evaluation plans on the task's reward alone.

Choices (DreamerV2's ``Plan2Explore`` where it has one):

* the heads read the features of step t and predict step t+1 (``disag_offset: 1``), with no action
  input (``disag_action_cond: False``), so the bonus is a function of a plan state alone, like the
  reward head the planners already read;
* the target is the next observation in the world model's input space (symlog of the state
  vector), not the stochastic latent: 78 numbers for quadruped against 512, so the ensemble costs
  less than half of a plan state's other heads;
* the disagreement (std over heads, mean over the target's dimensions) is divided by its running
  mean on replay batches (bias-corrected EMA), so ``scale`` 1 weighs an average state's novelty
  like a reward of 1 per step, whatever the task's units.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from mjx_collo import nets
from mjx_collo.config import DisagConfig
from mjx_collo.planners.protocol import LatentModel

EMA = 0.99  # decay of the disagreement's running mean


@struct.dataclass
class ExplorerState:
    """The ensemble (``params``: the heads' variables stacked on a leading axis), its optimizer
    state, and the disagreement's running mean (``norm_sum`` / ``norm_weight``: an EMA and its
    bias correction)."""

    params: Any
    opt_state: optax.OptState
    norm_sum: jax.Array
    norm_weight: jax.Array


def _net(cfg: DisagConfig, out: int) -> nets.MLP:
    return nets.MLP(cfg.layers, cfg.units, out=out, act="elu")


def _optimizer(cfg: DisagConfig) -> optax.GradientTransformation:
    return optax.chain(optax.clip_by_global_norm(100.0), optax.adam(cfg.lr))


def init(cfg: DisagConfig, key: jax.Array, feat_dim: int, target_dim: int) -> ExplorerState:
    """``cfg.heads`` independently initialised heads ``[F] -> [target_dim]``."""
    keys = jax.random.split(key, cfg.heads)
    params = jax.vmap(lambda k: _net(cfg, target_dim).init(k, jnp.zeros((1, feat_dim))))(keys)
    return ExplorerState(
        params=params,
        opt_state=_optimizer(cfg).init(params),
        norm_sum=jnp.zeros((), jnp.float32),
        norm_weight=jnp.zeros((), jnp.float32),
    )


def _target_dim(cfg: DisagConfig, params: Any) -> int:
    """The heads' output width, read off their last layer (static)."""
    return int(params["params"][f"Dense_{cfg.layers}"]["kernel"].shape[-1])


def predictions(cfg: DisagConfig, params: Any, feat: jax.Array) -> jax.Array:
    """Every head's prediction: ``feat [..., F] -> [heads, ..., D]``."""
    net = _net(cfg, _target_dim(cfg, params))
    return jax.vmap(lambda p: net.apply(p, feat))(params)


def disagreement(cfg: DisagConfig, params: Any, feat: jax.Array) -> jax.Array:
    """Std over heads, mean over the target's dimensions: ``[..., F] -> [...]``."""
    return jnp.mean(jnp.std(predictions(cfg, params, feat), axis=0), axis=-1)


def norm(state: ExplorerState) -> jax.Array:
    """The running mean of the disagreement on replay (1 before the first update)."""
    return jnp.where(
        state.norm_weight > 0, state.norm_sum / jnp.maximum(state.norm_weight, 1e-8), 1
    )


def train_step(
    cfg: DisagConfig, state: ExplorerState, feat: jax.Array, target: jax.Array, mask: jax.Array
) -> tuple[ExplorerState, dict[str, jax.Array]]:
    """One Adam step of every head on the same pairs (``feat [N, F]`` -> ``target [N, D]``,
    ``mask [N]``: 0 where the pair crosses an episode boundary); the heads differ by their
    initialisation, as in Plan2Explore. Updates the running mean with this batch's disagreement."""
    feat = jax.lax.stop_gradient(feat)
    target = jax.lax.stop_gradient(target)
    weight = mask / jnp.maximum(jnp.sum(mask), 1.0)

    def loss_fn(params):
        pred = predictions(cfg, params, feat)  # [K, N, D]
        err = jnp.mean(jnp.square(pred - target[None]), axis=-1)  # [K, N]
        return jnp.sum(jnp.mean(err, axis=0) * weight), pred

    (loss, pred), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params)
    updates, opt_state = _optimizer(cfg).update(grads, state.opt_state, state.params)
    params = optax.apply_updates(state.params, updates)
    disag = jnp.sum(jnp.mean(jnp.std(pred, axis=0), axis=-1) * weight)
    new = ExplorerState(
        params=params,
        opt_state=opt_state,
        norm_sum=EMA * state.norm_sum + (1 - EMA) * disag,
        norm_weight=EMA * state.norm_weight + (1 - EMA),
    )
    # a non-finite batch (the world model's update is skipped then too) leaves the heads as they were
    finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves((loss, grads))]))
    state = jax.tree.map(lambda n, o: jnp.where(finite, n, o), new, state)
    return state, {
        "explore/disag_loss": loss,
        "explore/disag": disag,
        "explore/disag_norm": norm(state),
    }


def bonus_params(state: ExplorerState) -> tuple[Any, jax.Array]:
    """What a plan reads of the explorer: (heads, running mean)."""
    return state.params, norm(state)


def exploring_model(model: LatentModel, cfg: DisagConfig, scale: Any) -> LatentModel:
    """``model`` whose reward adds ``scale`` x the normalised disagreement of each plan state's
    features. Its params are ``(model's params, bonus_params(state))``; everything but the
    reward reads the model's own params unchanged (value, policy prior, transitions)."""
    if model.feat is None:
        raise ValueError("the disagreement bonus reads plan states' features: model.feat is None")

    def bonus_feat(b, f):
        heads, n = b
        return scale * disagreement(cfg, heads, f) / jnp.maximum(n, 1e-8)

    def bonus(q, z):
        return bonus_feat(q[1], model.feat(q[0], z))

    def step_reward(q, z, a):
        nz, r = model.step_reward(q[0], z, a)
        return nz, r + bonus(q, z)

    def step_reward_value(q, z, a):
        nz, r, v = model.step_reward_value(q[0], z, a)
        return nz, r + bonus(q, z), v

    def pass0(fn):
        return None if fn is None else (lambda q, *args: fn(q[0], *args))

    return LatentModel(
        start=pass0(model.start),
        step=pass0(model.step),
        reward=lambda q, z: model.reward(q[0], z) + bonus(q, z),
        value=pass0(model.value),
        feat=pass0(model.feat),
        ctx_feat=pass0(model.ctx_feat),
        step_reward=None if model.step_reward is None else step_reward,
        step_reward_value=None if model.step_reward_value is None else step_reward_value,
        step_feat=pass0(model.step_feat),
        feat_reward=None
        if model.feat_reward is None
        else (lambda q, f: model.feat_reward(q[0], f) + bonus_feat(q[1], f)),
        feat_value=pass0(model.feat_value),
        policy=pass0(model.policy),
        ctx_policy=pass0(model.ctx_policy),
    )

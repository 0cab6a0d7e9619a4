"""Dreamer actor-critic baseline (docs/ALGORITHM.md §2.1, Dreamer v1 with this project's conventions).

Imagine ``actor.horizon`` steps from (stop-gradient) posterior starts with a tanh-normal actor,
score them with lambda-returns of the frozen target value, and train the actor by backpropagating
the returns through the learned dynamics (``actor_grad = dynamics``); the value regresses onto the
same returns. The value convention is the planner's (value.py): ``V(f_k)`` excludes the reward of
its own state, so ``y_k = r_{k+1} + gamma [(1 - lam) V'(f_{k+1}) + lam y_{k+1}]`` for
k = 0..H-1, with ``y_{H-1} = r_H + gamma V'(f_H)``, and ``actor_loss = -mean(sum_k w_k y_k) / H``
with ``w_k = gamma^k``.

Imagination protocol (:class:`ImaginationModel`, built by ``world_model.imagination_model``):
``img_step(params, state, a, key) -> state`` (stochastic prior step, batched over leading dims),
``get_feat(state) -> [..., F]``, ``reward(params, feat) -> [...]``. The value network comes from
:mod:`mjx_collo.value`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from mjx_collo import nets
from mjx_collo import value as value_lib
from mjx_collo.config import ActorConfig, Config

Params = Any
State = Any


class ImaginationModel(NamedTuple):
    """Stochastic latent dynamics for imagination (all batched over leading dims).

    img_step: ``(params, state, a [..., A], key) -> state``; get_feat: ``state -> [..., F]``;
    reward: ``(params, feat [..., F]) -> [...]`` reward of arriving in that state.
    """

    img_step: Callable[[Params, State, jax.Array, jax.Array], State]
    get_feat: Callable[[State], jax.Array]
    reward: Callable[[Params, jax.Array], jax.Array]


@struct.dataclass
class ActorState:
    """Actor network variables and optimiser state."""

    params: Any
    opt_state: optax.OptState


def actor_net(cfg: ActorConfig, action_dim: int) -> nets.MLP:
    """``layers`` x ``units`` ELU MLP -> [mean, std] pre-activations (D1: 4 x 400)."""
    return nets.MLP(cfg.layers, cfg.units, out=2 * action_dim, act="elu")


def init_actor(cfg: ActorConfig, key: jax.Array, feat_dim: int, action_dim: int) -> ActorState:
    variables = actor_net(cfg, action_dim).init(key, jnp.zeros((1, feat_dim)))
    return ActorState(
        params=variables, opt_state=value_lib.make_optimizer(cfg.optim).init(variables["params"])
    )


def dist_params(
    cfg: ActorConfig, params: Any, feat: jax.Array, action_dim: int
) -> tuple[jax.Array, jax.Array]:
    """Pre-tanh Normal(mean, std), D1: mean = s tanh(mu / s), std = softplus(u + softplus^-1(init))
    + min_std. feat: [..., F] -> ([..., A], [..., A])."""
    out = actor_net(cfg, action_dim).apply(params, feat)
    mu, u = out[..., :action_dim], out[..., action_dim:]
    mean = cfg.mean_scale * jnp.tanh(mu / cfg.mean_scale)
    raw_init = jnp.log(jnp.expm1(jnp.asarray(cfg.init_std, jnp.float32)))
    std = jax.nn.softplus(u + raw_init) + cfg.min_std
    return mean, std


def sample(mean: jax.Array, std: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Reparameterised tanh-normal sample and its log-probability. -> ([..., A], [...])."""
    eps = jax.random.normal(key, mean.shape, mean.dtype)
    u = mean + std * eps
    logp_u = -0.5 * jnp.square(eps) - jnp.log(std) - 0.5 * np.log(2 * np.pi)
    # log |d tanh(u)/du| = log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u)), stable.
    log_det = 2.0 * (np.log(2.0) - u - jax.nn.softplus(-2.0 * u))
    return jnp.tanh(u), jnp.sum(logp_u - log_det, axis=-1)


def act(
    cfg: ActorConfig, params: Any, feat: jax.Array, key: jax.Array, training: bool
) -> jax.Array:
    """Environment action: a sample in training, the mode tanh(mean) at evaluation. -> [..., A]

    (D1 estimates the mode as the most likely of 100 samples; tanh of the Gaussian mean is the
    usual closed-form stand-in.)
    """
    action_dim = actor_net_out(params) // 2
    mean, std = dist_params(cfg, params, feat, action_dim)
    if training:
        return sample(mean, std, key)[0]
    return jnp.tanh(mean)


def actor_net_out(params: Any) -> int:
    """Output width of the actor head (2 A), read from its last Dense layer's parameters."""
    layers = params["params"]
    last = max(layers, key=lambda name: int(name.rsplit("_", 1)[-1]))
    return int(layers[last]["bias"].shape[-1])


def imagine(
    cfg: Config,
    model: ImaginationModel,
    wm_params: Params,
    actor_params: Any,
    starts: State,
    key: jax.Array,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Roll the actor through the model for ``actor.horizon`` steps from ``starts`` ([N, ...]).

    Returns feats [H+1, N, F] (f_0 = start), actions [H, N, A], log-probs [H, N]. The actor sees
    stop-gradient features (D1); gradients flow through the sampled actions into the dynamics.
    """
    action_dim = actor_net_out(actor_params) // 2
    horizon = cfg.actor.horizon

    def body(state, k):
        ka, ks = jax.random.split(k)
        f = jax.lax.stop_gradient(model.get_feat(state))
        mean, std = dist_params(cfg.actor, actor_params, f, action_dim)
        a, logp = sample(mean, std, ka)
        nxt = model.img_step(wm_params, state, a, ks)
        return nxt, (model.get_feat(nxt), a, logp)

    _, (feats, acts, logps) = jax.lax.scan(body, starts, jax.random.split(key, horizon))
    feats = jnp.concatenate([model.get_feat(starts)[None], feats], axis=0)
    return feats, acts, logps


def imagined_returns(
    cfg: Config, model: ImaginationModel, wm_params: Params, target: Any, feats: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """Lambda-returns of imagined features. feats: [H+1, N, F] -> (y [H, N], weights [H, 1])."""
    vc = cfg.value
    rewards = model.reward(wm_params, feats[1:])
    values = value_lib.clip_value(vc, value_lib.apply_value(vc, target, feats[1:]))
    y = value_lib.lambda_returns(rewards, values, jnp.ones_like(rewards), vc.gamma, vc.lam)
    y = value_lib.clip_value(vc, y)
    horizon = feats.shape[0] - 1
    w = jnp.power(jnp.asarray(vc.gamma, jnp.float32), jnp.arange(horizon, dtype=jnp.float32))
    return y, w[:, None]


def actor_loss(
    actor_params: Any,
    cfg: Config,
    model: ImaginationModel,
    wm_params: Params,
    target: Any,
    starts: State,
    key: jax.Array,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """-mean(w_k y_k) - entropy * mean(w_k H_k) (dynamics backprop; D1)."""
    feats, acts, logps = imagine(cfg, model, wm_params, actor_params, starts, key)
    y, w = imagined_returns(cfg, model, wm_params, target, feats)
    ent = -logps
    loss = -jnp.mean(w * y) - cfg.actor.entropy * jnp.mean(w * ent)
    aux = {"feats": feats, "targets": y, "weights": jnp.broadcast_to(w, y.shape), "entropy": ent}
    return loss, aux


def train_step(
    cfg: Config,
    model: ImaginationModel,
    wm_params: Params,
    astate: ActorState,
    vstate: value_lib.ValueState,
    starts: State,
    key: jax.Array,
) -> tuple[ActorState, value_lib.ValueState, dict[str, jax.Array]]:
    """One actor update (through the dynamics) and one value update on the same imagination.

    starts: posterior states [N, ...] (gradients stopped). A non-finite actor loss or gradient
    skips the actor update (``actor/nonfinite`` = 1).
    """
    k_img, k_val = jax.random.split(key)
    new_astate, aux, metrics = actor_step(
        cfg, model, wm_params, astate, vstate.target, starts, k_img
    )
    feats = jax.lax.stop_gradient(aux["feats"][:-1])
    targets = jax.lax.stop_gradient(aux["targets"])
    vstate, vmetrics = value_lib.update(cfg.value, vstate, feats, targets, aux["weights"], k_val)
    return new_astate, vstate, {**metrics, **vmetrics}


def actor_step(
    cfg: Config,
    model: ImaginationModel,
    wm_params: Params,
    astate: ActorState,
    target: Any,
    starts: State,
    key: jax.Array,
    bc: tuple[jax.Array, jax.Array, jax.Array] | None = None,
) -> tuple[ActorState, dict[str, jax.Array], dict[str, jax.Array]]:
    """The actor update alone, scored by the value ``target`` params: Dreamer's actor step, and
    the policy prior's (``planner.init: policy``), whose value is the planner's and learns its
    own way (``value.mode``). Returns (actor state, the imagination's aux, metrics).

    ``bc`` (the policy prior only): ``(feat [N, F], action [N, A], mask [N])``, replay features
    and the actions the agent took from them (the planner's, with exploration noise); the loss is
    then ``actor.pg`` x Dreamer's objective + ``actor.bc`` x :func:`bc_loss`."""
    starts = jax.lax.stop_gradient(starts)
    if bc is None:
        grad_fn = jax.value_and_grad(actor_loss, has_aux=True)
        (loss, aux), grads = grad_fn(astate.params, cfg, model, wm_params, target, starts, key)
        extra = {}
    else:
        bc = jax.lax.stop_gradient(bc)

        def prior_loss(params):
            loss_pg, aux = actor_loss(params, cfg, model, wm_params, target, starts, key)
            loss_bc = bc_loss(cfg.actor, params, *bc)
            return cfg.actor.pg * loss_pg + cfg.actor.bc * loss_bc, (aux, loss_pg, loss_bc)

        (loss, (aux, loss_pg, loss_bc)), grads = jax.value_and_grad(prior_loss, has_aux=True)(
            astate.params
        )
        extra = {"actor/loss_dynamics": loss_pg, "actor/loss_bc": loss_bc}
    grads = grads["params"]
    tx = value_lib.make_optimizer(cfg.actor.optim)
    upd, opt_state = tx.update(grads, astate.opt_state, astate.params["params"])
    new_p = optax.apply_updates(astate.params["params"], upd)
    new_p = jax.tree.map(lambda p: p * (1.0 - cfg.actor.optim.weight_decay), new_p)
    leaves = jax.tree.leaves((loss, grads))
    finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves]))
    new_astate = ActorState(params={**astate.params, "params": new_p}, opt_state=opt_state)
    new_astate = jax.tree.map(lambda n, o: jnp.where(finite, n, o), new_astate, astate)
    metrics = {
        "actor/loss": loss,
        "actor/imag_return": jnp.mean(aux["targets"][0]),
        "actor/entropy": jnp.mean(aux["entropy"]),
        "actor/grad_norm": optax.global_norm(grads),
        "actor/nonfinite": (~finite).astype(jnp.float32),
        **extra,
    }
    return new_astate, aux, metrics


def bc_loss(
    cfg: ActorConfig, params: Any, feat: jax.Array, action: jax.Array, mask: jax.Array
) -> jax.Array:
    """Behaviour cloning of the planner: mean squared error between the policy's deterministic
    action ``tanh(mean)`` and the action taken, over the ``mask``ed pairs. feat [N, F], action
    [N, A], mask [N] -> []. (The squared error of the mode, not the log-likelihood: the taken
    actions carry exploration noise, which the mean should average out, not learn as spread.)"""
    pred = mode(cfg, params, feat, action.shape[-1])
    err = jnp.mean(jnp.square(pred - action), axis=-1)
    return jnp.sum(mask * err) / jnp.maximum(jnp.sum(mask), 1.0)


def mode(cfg: ActorConfig, params: Any, feat: jax.Array, action_dim: int) -> jax.Array:
    """The deterministic action tanh(mean) on features ``[..., F]`` (evaluation, policy prior)."""
    return jnp.tanh(dist_params(cfg, params, feat, action_dim)[0])


def flatten_starts(states: State, batch_ndim: int) -> State:
    """Merge the leading ``batch_ndim`` dims of every leaf (e.g. posterior [B, T, ...] -> [B*T, ...])."""
    return jax.tree.map(lambda x: x.reshape((-1,) + x.shape[batch_ndim:]), states)

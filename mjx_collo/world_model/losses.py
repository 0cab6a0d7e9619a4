"""The world model's training: the ELBO with KL balancing (docs/ALGORITHM.md §1.4), the J_latent
surrogate (§4.5), and the update — gradients through the time scan's "taps" and one optimizer over
the flat parameter vector.

Float config fields (``kl.*``, ``loss_scales.*``, ``optim.*``) may be JAX tracers inside a swept
program, so nothing here branches on them in Python.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import struct
from jax.flatten_util import ravel_pytree

from mjx_collo.config import JLatentConfig, OptimConfig, WorldModelConfig
from mjx_collo.world_model.dists import entropy, kl_div, log_prob
from mjx_collo.world_model.heads import (
    _reward_mean,
    _reward_nll,
    _reward_out,
    decode,
    is_pixel,
    preprocess_obs,
)
from mjx_collo.world_model.rssm import (
    RECURRENT,
    RSSMState,
    Taps,
    _observe_io,
    _stat_size,
    _transition,
    get_feat,
    prior_stats,
)

Params = dict[str, Any]
Batch = dict[str, jax.Array]


@struct.dataclass
class Posterior:
    """What the trainer needs from a world-model update (all stop-gradient), ``[B, T, ...]``.

    feat: posterior features ``[B, T, F]``; reward: observed ``r_t`` ``[B, T]``; is_first ``[B, T]``;
    action: ``a_{t-1}`` ``[B, T, A]``; state: the posterior :class:`RSSMState`.
    """

    feat: jax.Array
    reward: jax.Array
    is_first: jax.Array
    action: jax.Array
    state: RSSMState


def kl_loss(
    cfg: WorldModelConfig, post: dict[str, jax.Array], prior: dict[str, jax.Array]
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """KL balancing with free nats on the batch mean of each term (D2 ``free_avg``).

    ``L = a * max(mean KL[sg(q) || p], free) + (1 - a) * max(mean KL[q || sg(p)], free)``
    with ``a = cfg.kl.balance``: a fraction ``a`` of the KL gradient trains the prior, ``1 - a``
    the posterior. Stats are ``[B, T, ...]``; returns (scalar loss, metrics).
    """
    sg = jax.lax.stop_gradient
    kl_prior = jnp.mean(kl_div(cfg, jax.tree.map(sg, post), prior))
    kl_post = jnp.mean(kl_div(cfg, post, jax.tree.map(sg, prior)))
    dyn = cfg.kl.balance * jnp.maximum(kl_prior, cfg.kl.free)
    rep = (1.0 - cfg.kl.balance) * jnp.maximum(kl_post, cfg.kl.free)
    return dyn + rep, {"kl": kl_prior, "kl/prior_term": dyn, "kl/post_term": rep}


class JLatentArgs(NamedTuple):
    """Inputs of the J_latent surrogate (docs/ALGORITHM.md §4.5); pass to :func:`loss` when enabled.

    old_params: the frozen world model ``phi_old``; value_fn: ``feat [..., F] -> v [...]``;
    beta: weight ``beta_lat`` (scalar array); gamma: discount; cfg: the ``j_latent`` section.
    """

    old_params: Params
    value_fn: Callable[[jax.Array], jax.Array]
    beta: jax.Array
    gamma: Any
    cfg: JLatentConfig


def _one_step_logp(
    cfg: WorldModelConfig, params: Params, post: RSSMState, action: jax.Array
) -> jax.Array:
    """``log p_phi(s_t | h_t(phi))`` with ``h_t(phi) = GRU_phi(sg s_{t-1}, a_{t-1}, sg h_{t-1})``.

    post ``[B, T]`` (stop-gradient), action ``[B, T, A]`` -> ``[B, T-1]`` for t = 1..T-1.
    """
    deter = _transition(cfg, params, post.stoch[:, :-1], post.deter[:, :-1], action[:, 1:])
    return log_prob(cfg, prior_stats(cfg, params, deter), post.stoch[:, 1:])


def j_latent(
    cfg: WorldModelConfig,
    params: Params,
    jl: JLatentArgs,
    post: RSSMState,
    action: jax.Array,
    rew: jax.Array,
    is_first: jax.Array,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Clipped-ratio surrogate J_latent on the world-model parameters (paper Eq. 11, §4.5).

    ``log m_t = l_t + l_{t-1}``, ``l_t = log p_phi(s_t|h_t(phi)) - log p_old(s_t|h_t(old))``;
    ``A_t = sg(r_t + gamma V(f_t) - V(f_{t-1}))`` (V excludes its own reward: it credits the
    transition into t with r_t); ``J = mean_t min(e^{clip(log m)} A, clip(e^{log m}, 1 +- eps) A)``
    over t = 2..T-1 where no reset falls in the window. Inputs ``[B, T, ...]``, stop-gradient.
    Returns (J, metrics) — J is to be *maximised*.
    """
    sg = jax.lax.stop_gradient
    post = jax.tree.map(sg, post)
    old = jax.tree.map(sg, jl.old_params)
    lr = _one_step_logp(cfg, params, post, action) - _one_step_logp(cfg, old, post, action)
    log_m = lr[:, 1:] + lr[:, :-1]  # t = 2..T-1
    value = jl.value_fn(get_feat(post))  # [B, T]
    adv = sg(rew[:, 2:] + jl.gamma * value[:, 2:] - value[:, 1:-1])
    valid = ~(is_first[:, 2:] | is_first[:, 1:-1] | is_first[:, :-2])
    log_m = jnp.clip(log_m, -jl.cfg.log_ratio_clip, jl.cfg.log_ratio_clip)
    ratio = jnp.exp(log_m)
    clipped = jnp.clip(ratio, 1.0 - jl.cfg.ratio_clip, 1.0 + jl.cfg.ratio_clip)
    surr = jnp.minimum(ratio * adv, clipped * adv)
    w = valid.astype(jnp.float32)
    denom = jnp.maximum(jnp.sum(w), 1.0)
    obj = jnp.sum(w * surr) / denom
    return obj, {"j_latent": obj, "j_latent_log_ratio": jnp.sum(w * jnp.abs(log_m)) / denom}


def loss_scales(cfg: WorldModelConfig) -> dict[str, Any]:
    """The scale table: total loss = sum_k scale_k * loss_k."""
    return {
        "obs": cfg.loss_scales.obs,
        "reward": cfg.loss_scales.reward,
        "kl": cfg.loss_scales.kl * cfg.kl.scale,
    }


def loss(
    cfg: WorldModelConfig,
    params: Params,
    batch: Batch,
    key: jax.Array,
    jlat: JLatentArgs | None = None,
    unroll: int | bool = 1,
) -> tuple[jax.Array, dict[str, jax.Array], dict[str, jax.Array], Posterior]:
    """World-model ELBO (docs/ALGORITHM.md §1.4) on a replay batch.

    batch: ``obs [B, T, *obs_shape]``, ``action [B, T, A]`` (a_{t-1}), ``reward [B, T]`` (r_t),
    ``is_first [B, T]``. Terms (means over B, T; Gaussian NLLs with unit variance, constants
    dropped): ``obs = 0.5 * sum_obs (dec(f_t) - o_t)^2``, ``reward = 0.5 (r̂(f_t) - r_t)^2``
    (``reward_head: twohot``: the two-hot cross-entropy, :func:`reward_nll`),
    ``kl`` = :func:`kl_loss`; with ``jlat``, ``j_latent`` = -J with scale ``jlat.beta``.
    Returns (total, losses, metrics, posterior outputs for the trainer).
    """
    return _loss_io(cfg, params, batch, key, jlat, unroll)[:4]


def _loss_io(
    cfg: WorldModelConfig,
    params: Params,
    batch: Batch,
    key: jax.Array,
    jlat: JLatentArgs | None = None,
    unroll: int | bool = 1,
    taps: Taps | None = None,
) -> tuple[jax.Array, dict[str, jax.Array], dict[str, jax.Array], Posterior, dict[str, jax.Array]]:
    """:func:`loss` plus the scanned dense layers' inputs (see :func:`_observe_io`)."""
    obs, action, first = batch["obs"], batch["action"], batch["is_first"]
    post, prior, inputs = _observe_io(cfg, params, obs, action, first, key, None, unroll, taps)
    feat = get_feat(post)
    # Pixels with wm.decode_every = k: the image term is the mean over every k-th frame of each
    # sequence (an unbiased estimate of the full term's mean; replay sequences start anywhere, so
    # every frame is decoded in some batches). The decoder is ~half a pixel update's time on CPU.
    k = cfg.decode_every if is_pixel(params) else 1
    target = preprocess_obs(cfg, params, batch["obs"][:, ::k])
    sq_obs = jnp.square(decode(cfg, params, feat[:, ::k]) - target)
    rew = batch["reward"].astype(jnp.float32)
    rew_out = _reward_out(cfg, params, feat)  # one pass of the head: the loss and the error metric
    sq_rew = jnp.square(_reward_mean(cfg, rew_out) - rew)
    obs_axes = tuple(range(2, sq_obs.ndim))
    kl, kl_metrics = kl_loss(cfg, post.stats, prior.stats)
    rew_loss = 0.5 * sq_rew if cfg.reward_head == "mse" else _reward_nll(cfg, rew_out, rew)
    losses = {"obs": 0.5 * jnp.mean(jnp.sum(sq_obs, obs_axes)), "reward": jnp.mean(rew_loss)}
    losses["kl"] = kl
    scales = loss_scales(cfg)
    metrics = dict(kl_metrics)
    if jlat is not None:
        obj, jl_metrics = j_latent(cfg, params, jlat, post, batch["action"], rew, batch["is_first"])
        losses["j_latent"] = -obj
        scales["j_latent"] = jlat.beta
        metrics.update(jl_metrics)
    total = sum(scales[k] * v for k, v in losses.items())
    metrics.update({f"loss/{k}": v for k, v in losses.items()})
    metrics.update(
        {
            "ent/prior": jnp.mean(entropy(cfg, prior.stats)),
            "ent/post": jnp.mean(entropy(cfg, post.stats)),
            "err/obs_mse": jnp.mean(sq_obs),
            "err/reward_mse": jnp.mean(sq_rew),
        }
    )
    sg = jax.lax.stop_gradient
    out = Posterior(
        feat=sg(feat),
        reward=rew,
        is_first=batch["is_first"],
        action=batch["action"],
        state=jax.tree.map(sg, post),
    )
    return total, losses, metrics, out, inputs


def make_optimizer(cfg: OptimConfig) -> optax.GradientTransformation:
    """The one optimizer path: global-norm clip -> Adam(eps) -> -lr -> decoupled weight decay.

    Weight decay follows D2 (``var <- (1 - wd) * var`` per step, not scaled by lr). Reads float
    config values, so build it inside traced code when they may be tracers.
    """
    return optax.chain(
        optax.clip_by_global_norm(cfg.clip),
        optax.scale_by_adam(eps=cfg.eps),
        optax.scale_by_learning_rate(cfg.lr),
        optax.add_decayed_weights(-cfg.weight_decay),
    )


def init_opt_state(cfg: WorldModelConfig, params: Params) -> optax.OptState:
    """Optimizer state for :func:`train_step`, over the flattened parameter vector (one Adam
    kernel instead of one per layer: faster to compile and to run on CPU). Its structure does not
    depend on float config values."""
    return make_optimizer(cfg.optim).init(ravel_pytree(params)[0])


def _zero_taps(cfg: WorldModelConfig, steps: int, batch: int) -> Taps:
    out = {
        "img_in": cfg.hidden,
        "gru": 3 * cfg.deter,
        "obs_h": cfg.hidden,
        "obs_out": _stat_size(cfg),
    }
    return {k: jnp.zeros((steps, batch, n)) for k, n in out.items()}


def value_and_grad(
    cfg: WorldModelConfig,
    params: Params,
    batch: Batch,
    key: jax.Array,
    jlat: JLatentArgs | None = None,
    unroll: int | bool = 1,
) -> tuple[tuple[jax.Array, dict[str, jax.Array], Posterior], jax.Array]:
    """Loss and its gradient w.r.t. the flattened parameters (``ravel_pytree(params)``).

    Same value as ``jax.value_and_grad`` of :func:`loss`, computed faster on CPU: the dense
    layers inside the time scan get their weight gradients as one ``[T*B, in] x [T*B, out]``
    matmul each, outside the scan, instead of T small accumulations inside the backward scan
    (their outputs carry zero "taps" whose cotangents are the per-step output gradients).
    Returns ((total, metrics, posterior outputs), flat gradient).
    """
    flat, unravel = ravel_pytree(params)
    steps, size = batch["is_first"].shape[1], batch["is_first"].shape[0]

    def objective(f: jax.Array, taps: Taps):
        total, _, metrics, out, inputs = _loss_io(cfg, unravel(f), batch, key, jlat, unroll, taps)
        return total, (metrics, out, inputs)

    (total, (metrics, out, inputs)), (g_flat, g_taps) = jax.value_and_grad(
        objective, argnums=(0, 1), has_aux=True
    )(flat, _zero_taps(cfg, steps, size))
    dense = {
        name: {
            "kernel": jnp.einsum("tbi,tbo->io", inputs[name], g_taps[name]),
            "bias": jnp.sum(g_taps[name], (0, 1)),
        }
        for name in RECURRENT
    }
    extra = jax.tree.map(jnp.zeros_like, params)
    for name in RECURRENT:
        extra[name] = {**extra[name], "Dense_0": dense[name]}
    return (total, metrics, out), g_flat + ravel_pytree(extra)[0]


def train_step(
    cfg: WorldModelConfig,
    params: Params,
    opt_state: optax.OptState,
    batch: Batch,
    key: jax.Array,
    jlat: JLatentArgs | None = None,
    unroll: int | bool = 1,
) -> tuple[Params, optax.OptState, dict[str, jax.Array], Posterior]:
    """One world-model update. Skips it (returns the inputs) when the loss or the gradients are
    non-finite, reporting ``metrics["nonfinite"] = 1``.

    Returns (params, opt_state, scalar metrics, :class:`Posterior` of the batch under the
    pre-update params, for value learning).
    """
    flat, unravel = ravel_pytree(params)
    (total, metrics, out), grads = value_and_grad(cfg, params, batch, key, jlat, unroll)
    grad_norm = optax.global_norm(grads)
    finite = jnp.isfinite(total) & jnp.isfinite(grad_norm)
    updates, new_opt = make_optimizer(cfg.optim).update(grads, opt_state, flat)
    new_flat = jnp.where(finite, flat + updates, flat)
    new_opt = jax.tree.map(lambda n, o: jnp.where(finite, n, o), new_opt, opt_state)
    metrics = {
        **metrics,
        "loss/total": total,
        "grad_norm": grad_norm,
        "nonfinite": (~finite).astype(jnp.float32),
    }
    return unravel(new_flat), new_opt, metrics, out

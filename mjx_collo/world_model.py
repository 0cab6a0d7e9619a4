"""Recurrent state-space world model (Dreamer v1 Gaussian / DreamerV2 categorical RSSM).

Pure functions over a parameter pytree (DESIGN rules 6, 7, 10); the flax modules live in nets.py.
Every function takes the static :class:`~mjx_collo.config.WorldModelConfig` first; its float fields
(``min_std``, ``unimix``, ``kl.*``, ``loss_scales.*``, ``optim.*``) may be JAX tracers inside a swept
program, so nothing here branches on them in Python.

Notation (ALGORITHM.md §1): ``h`` deterministic GRU state ``[..., D]``; ``s`` stochastic state, flat
``[..., S]`` (gaussian: ``S = stoch``; categorical: ``S = stoch * classes`` one-hot groups); feature
``f = [s, h]`` of size ``F = S + D``; ``e = enc(o)`` embedding ``[..., E]``.

Data convention (the LC/D1 one, shared with replay.py): row ``t`` of a sequence holds ``obs_t``, the
action ``a_{t-1}`` that led into ``obs_t``, the reward ``r_t`` received on arriving in ``obs_t``, and
``is_first_t``. The posterior at ``t`` is ``q(s_t | h_t, e_t)`` with ``h_t = GRU(s_{t-1}, a_{t-1},
h_{t-1})``; at ``is_first`` the previous state *and* the previous action are reset to zeros. The
reward head ``r̂(f_t)`` predicts ``r_t``.

Speed (CPU, measured by benchmarks/bench_model.py): inside the ``lax.scan`` over time only the
recurrent chain runs (input layer, GRU, posterior layers, sample). The encoder, the embedding half
of the posterior layer, the prior head, the decoder and the reward head are applied to all ``B*T``
rows at once outside the scan; the sampling noise for all steps is drawn in one call (one uniform
per categorical group: inverse-CDF sampling); the weight gradients of the scanned dense layers are
formed after the scan as one large matmul each (:func:`value_and_grad`); the optimizer runs on the
flat parameter vector.

Main entry points: :func:`init`, :func:`observe` / :func:`obs_step` (posterior filtering),
:func:`img_step` / :func:`imagine` / :func:`imagine_policy` (prior), :func:`loss`,
:func:`value_and_grad`, :func:`train_step`, :func:`planning_fns` and :func:`imagine_fns`
(protocols for the planner and the Dreamer actor), :func:`j_latent`.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import struct
from jax.flatten_util import ravel_pytree

from mjx_collo import nets
from mjx_collo.config import JLatentConfig, OptimConfig, WorldModelConfig

Params = dict[str, Any]
Batch = dict[str, jax.Array]
PIXEL_NDIM = 3  # [H, W, C]

# --------------------------------------------------------------------------------------------
# State and networks
# --------------------------------------------------------------------------------------------


@struct.dataclass
class RSSMState:
    """One RSSM state (any leading batch/time shape ``...``).

    deter: ``[..., D]``; stoch: ``[..., S]`` sample (categorical: straight-through one-hot, flat);
    stats: gaussian ``{"mean": [..., s], "std": [..., s]}``, categorical
    ``{"logits": [..., G, K]}`` (normalised log-probabilities, unimix applied).
    """

    deter: jax.Array
    stoch: jax.Array
    stats: dict[str, jax.Array]


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


def stoch_size(cfg: WorldModelConfig) -> int:
    """S: flat size of the stochastic state."""
    return cfg.stoch * (cfg.classes if cfg.latent == "categorical" else 1)


def feat_size(cfg: WorldModelConfig) -> int:
    """F = S + D."""
    return stoch_size(cfg) + cfg.deter


def _stat_size(cfg: WorldModelConfig) -> int:
    return 2 * cfg.stoch if cfg.latent == "gaussian" else cfg.stoch * cfg.classes


def _rssm_nets(cfg: WorldModelConfig) -> dict[str, Any]:
    stat = _stat_size(cfg)
    return {
        "img_in": nets.Linear(cfg.hidden),
        "gru": nets.GRUCell(cfg.deter, layernorm=cfg.gru_layernorm),
        "img_out": nets.MLP(1, cfg.hidden, out=stat, act=cfg.act),
        "obs_h": nets.Linear(cfg.hidden),
        "obs_e": nets.Linear(cfg.hidden, bias=False),
        "obs_out": nets.Linear(stat),
        "reward": _reward_net(cfg),
    }


def _reward_net(cfg: WorldModelConfig) -> Any:
    out = cfg.reward_bins if cfg.reward_head == "twohot" else 1
    return nets.MLP(cfg.reward_layers, cfg.units, out=out, act=cfg.act)


def _io_nets(cfg: WorldModelConfig, obs_shape: tuple[int, ...]) -> dict[str, Any]:
    """Encoder/decoder; the dict key records the kind (``*_conv`` for pixels) in the params."""
    if len(obs_shape) == PIXEL_NDIM:
        return {
            "enc_conv": nets.ConvEncoder(cfg.cnn_depth),
            "dec_conv": nets.ConvDecoder(obs_shape[-1], cfg.cnn_depth),
        }
    (dim,) = obs_shape
    return {
        "enc_mlp": nets.MLP(cfg.enc_layers, cfg.units, act=cfg.act),
        "dec_mlp": nets.MLP(cfg.dec_layers, cfg.units, out=dim, act=cfg.act),
    }


def _apply(module: Any, p: Params, *args: jax.Array) -> jax.Array:
    return module.apply({"params": p}, *args)


def init(
    cfg: WorldModelConfig, key: jax.Array, obs_shape: tuple[int, ...], action_dim: int
) -> Params:
    """World-model parameters for observations ``obs_shape`` (``(O,)`` or ``(64, 64, C)``)."""
    obs_shape = tuple(int(n) for n in obs_shape)
    try:
        fn = _jitted_init(cfg, obs_shape, action_dim)  # compiled once per config
    except TypeError:  # unhashable config (traced swept values): trace inline
        fn = functools.partial(_init, cfg, obs_shape, action_dim)
    return fn(key)


@functools.lru_cache(maxsize=16)
def _jitted_init(cfg: WorldModelConfig, obs_shape: tuple[int, ...], action_dim: int):
    return jax.jit(functools.partial(_init, cfg, obs_shape, action_dim))


def _init(
    cfg: WorldModelConfig, obs_shape: tuple[int, ...], action_dim: int, key: jax.Array
) -> Params:
    mods = {**_rssm_nets(cfg), **_io_nets(cfg, obs_shape)}
    s, d, h = stoch_size(cfg), cfg.deter, cfg.hidden
    enc_name = "enc_conv" if len(obs_shape) == PIXEL_NDIM else "enc_mlp"
    x = jax.ShapeDtypeStruct((1,) + obs_shape, jnp.float32)
    embed_dim = jax.eval_shape(lambda x: mods[enc_name].init_with_output(key, x)[0], x).shape[-1]
    z = lambda *shape: jax.ShapeDtypeStruct((1, *shape), jnp.float32)
    dummy = {
        "img_in": (z(s + action_dim),),
        "gru": (z(h), z(d)),
        "img_out": (z(d),),
        "obs_h": (z(d),),
        "obs_e": (z(embed_dim),),
        "obs_out": (z(h),),
        "reward": (z(s + d),),
        "enc_mlp": (z(*obs_shape),),
        "enc_conv": (z(*obs_shape),),
        "dec_mlp": (z(s + d),),
        "dec_conv": (z(s + d),),
    }

    specs = {name: (mod, dummy[name]) for name, mod in mods.items()}
    # The two-hot head keeps the default random output layer. D3 zeroes it (a fresh head predicts
    # 0), but then no reward gradient reaches the hidden layers or the latent until that layer
    # has grown: on a sparse toy reward the zeroed head still predicted the base rate after 200
    # updates, where the random one had fit it (err/reward_mse 0.50 vs 0.02).
    return nets.init_many(specs, key)


def _is_pixel(params: Params) -> bool:
    return "enc_conv" in params


# --------------------------------------------------------------------------------------------
# Observations
# --------------------------------------------------------------------------------------------


def symlog(x: jax.Array) -> jax.Array:
    return jnp.sign(x) * jnp.log1p(jnp.abs(x))


def symexp(x: jax.Array) -> jax.Array:
    return jnp.sign(x) * jnp.expm1(jnp.abs(x))


def preprocess_obs(cfg: WorldModelConfig, params: Params, obs: jax.Array) -> jax.Array:
    """Raw observations -> network space (the encoder input and the decoder target).

    Pixels (uint8 or float in [0, 255]): ``x / 255 - 0.5``; vectors: ``symlog(x)`` if
    ``cfg.symlog_obs`` else ``x``. Shape unchanged, float32.
    """
    x = obs.astype(jnp.float32)
    if _is_pixel(params):
        return x / 255.0 - 0.5
    return symlog(x) if cfg.symlog_obs else x


def postprocess_obs(cfg: WorldModelConfig, params: Params, x: jax.Array) -> jax.Array:
    """Inverse of :func:`preprocess_obs` (decoder output -> raw observation units)."""
    if _is_pixel(params):
        return (x + 0.5) * 255.0
    return symexp(x) if cfg.symlog_obs else x


def encode(cfg: WorldModelConfig, params: Params, obs: jax.Array) -> jax.Array:
    """``obs: [..., *obs_shape]`` raw -> embedding ``[..., E]``."""
    x = preprocess_obs(cfg, params, obs)
    if _is_pixel(params):
        return _apply(nets.ConvEncoder(cfg.cnn_depth), params["enc_conv"], x)
    return _apply(nets.MLP(cfg.enc_layers, cfg.units, act=cfg.act), params["enc_mlp"], x)


def decode(cfg: WorldModelConfig, params: Params, feat: jax.Array) -> jax.Array:
    """``feat: [..., F]`` -> predicted observation mean in network space ``[..., *obs_shape]``."""
    if _is_pixel(params):
        channels = params["dec_conv"]["ConvTranspose_3"]["kernel"].shape[-1]
        return _apply(nets.ConvDecoder(channels, cfg.cnn_depth), params["dec_conv"], feat)
    dim = params["dec_mlp"][f"Dense_{cfg.dec_layers}"]["kernel"].shape[-1]
    mod = nets.MLP(cfg.dec_layers, cfg.units, out=dim, act=cfg.act)
    return _apply(mod, params["dec_mlp"], feat)


def predict_obs(cfg: WorldModelConfig, params: Params, feat: jax.Array) -> jax.Array:
    """``feat: [..., F]`` -> predicted observation in raw units ``[..., *obs_shape]``."""
    return postprocess_obs(cfg, params, decode(cfg, params, feat))


def reward(cfg: WorldModelConfig, params: Params, feat: jax.Array) -> jax.Array:
    """``feat: [..., F]`` -> predicted reward of arriving in that state ``[...]``.

    ``reward_head: twohot``: the head's logits over :func:`reward_bins` give
    ``symexp(sum_k softmax(logits)_k * bin_k)`` (DreamerV3's mean), differentiable in ``feat``.
    """
    return _reward_mean(cfg, _reward_out(cfg, params, feat))


def _reward_out(cfg: WorldModelConfig, params: Params, feat: jax.Array) -> jax.Array:
    """The reward head's raw output: ``[..., 1]`` (mse) or logits ``[..., reward_bins]``."""
    return _apply(_reward_net(cfg), params["reward"], feat)


def _reward_mean(cfg: WorldModelConfig, out: jax.Array) -> jax.Array:
    if cfg.reward_head == "twohot":
        return symexp(jnp.sum(jax.nn.softmax(out, -1) * reward_bins(cfg), -1))
    return out[..., 0]


def reward_bins(cfg: WorldModelConfig) -> jax.Array:
    """The two-hot head's bin centres in symlog space: ``reward_bins`` evenly from -20 to 20 (D3)."""
    return jnp.linspace(-20.0, 20.0, cfg.reward_bins)


def twohot(y: jax.Array, bins: jax.Array) -> jax.Array:
    """``y [...]`` -> ``[..., K]``: weight on the two bins around ``y`` (evenly spaced ``bins``),
    linear in the distance, so ``sum_k w_k bin_k = y`` inside the range; clipped outside it."""
    k = bins.shape[0]
    pos = jnp.clip((y - bins[0]) / (bins[-1] - bins[0]) * (k - 1), 0.0, k - 1.0)
    below = jnp.minimum(jnp.floor(pos), k - 2).astype(jnp.int32)
    frac = (pos - below)[..., None]
    return jax.nn.one_hot(below, k) * (1.0 - frac) + jax.nn.one_hot(below + 1, k) * frac


def reward_nll(cfg: WorldModelConfig, params: Params, feat: jax.Array, rew: jax.Array) -> jax.Array:
    """Per-step reward loss ``[...]``: ``0.5 (r̂ - r)^2`` (mse head), or the cross-entropy of the
    head's logits against ``twohot(symlog(r))`` (twohot head)."""
    return _reward_nll(cfg, _reward_out(cfg, params, feat), rew)


def _reward_nll(cfg: WorldModelConfig, out: jax.Array, rew: jax.Array) -> jax.Array:
    if cfg.reward_head == "twohot":
        target = twohot(symlog(rew), reward_bins(cfg))
        return -jnp.sum(target * jax.nn.log_softmax(out, -1), -1)
    return 0.5 * jnp.square(_reward_mean(cfg, out) - rew)


# --------------------------------------------------------------------------------------------
# Latent distributions
# --------------------------------------------------------------------------------------------


def _stats(cfg: WorldModelConfig, raw: jax.Array) -> dict[str, jax.Array]:
    """Raw head output ``[..., stat]`` -> distribution statistics (see :class:`RSSMState`)."""
    if cfg.latent == "gaussian":
        mean, u = jnp.split(raw, 2, axis=-1)
        return {"mean": mean, "std": jax.nn.softplus(u) + cfg.min_std}
    logits = raw.reshape(raw.shape[:-1] + (cfg.stoch, cfg.classes))
    logp = jax.nn.log_softmax(logits, axis=-1)
    # unimix: p <- (1 - u) p + u / K, in log space (u = 0 gives logp exactly, without log 0).
    # A literal 0.0 skips the work (as optax does); a traced value never branches.
    if not (isinstance(cfg.unimix, float) and cfg.unimix == 0.0):
        logp = jnp.logaddexp(jnp.log1p(-cfg.unimix) + logp, jnp.log(cfg.unimix / cfg.classes))
    return {"logits": logp}


def _noise(cfg: WorldModelConfig, key: jax.Array, batch: tuple[int, ...]) -> jax.Array:
    """Sampling noise ``[*batch, stoch]``: gaussian ``N(0, 1)``; categorical ``U[0, 1)``, one per
    group (inverse-CDF sampling: K times fewer random numbers than Gumbel-max)."""
    # Drawn flat and reshaped: XLA's CPU compile time for threefry grows steeply with the rank of
    # the drawn shape (~0.5 s flat vs ~4 s for rank 4).
    shape = batch + (cfg.stoch,)
    if cfg.latent == "gaussian":
        return jax.random.normal(key, (math.prod(shape),)).reshape(shape)
    return jax.random.uniform(key, (math.prod(shape),)).reshape(shape)


def _sample(cfg: WorldModelConfig, stats: dict[str, jax.Array], noise: jax.Array) -> jax.Array:
    """Reparameterised sample ``[..., S]``; categorical: ``onehot + p - sg(p)`` per group."""
    if cfg.latent == "gaussian":
        return stats["mean"] + stats["std"] * noise
    probs = jnp.exp(stats["logits"])
    # Inverse CDF: class k is drawn when cdf_{k-1} <= u < cdf_k (clipped for rounding at 1).
    cdf = jnp.cumsum(jax.lax.stop_gradient(probs), -1)
    index = jnp.minimum(jnp.sum(cdf <= noise[..., None], -1), cfg.classes - 1)
    onehot = jax.nn.one_hot(index, cfg.classes, dtype=probs.dtype)
    sample = onehot + probs - jax.lax.stop_gradient(probs)
    return sample.reshape(sample.shape[:-2] + (-1,))


def dist_mean(cfg: WorldModelConfig, stats: dict[str, jax.Array]) -> jax.Array:
    """Mean of the stochastic state ``[..., S]`` (categorical: probabilities, flat)."""
    if cfg.latent == "gaussian":
        return stats["mean"]
    probs = jnp.exp(stats["logits"])
    return probs.reshape(probs.shape[:-2] + (-1,))


def kl_div(cfg: WorldModelConfig, q: dict[str, jax.Array], p: dict[str, jax.Array]) -> jax.Array:
    """``KL[q || p]`` summed over the latent event (dims or groups) -> ``[...]``, float32."""
    if cfg.latent == "gaussian":
        var_ratio = jnp.square(q["std"] / p["std"])
        t1 = jnp.square((q["mean"] - p["mean"]) / p["std"])
        return 0.5 * jnp.sum(var_ratio + t1 - 1.0 - jnp.log(var_ratio), -1)
    lq, lp = q["logits"], p["logits"]
    return jnp.sum(jnp.exp(lq) * (lq - lp), (-2, -1))


def entropy(cfg: WorldModelConfig, stats: dict[str, jax.Array]) -> jax.Array:
    """Entropy summed over the latent event -> ``[...]``."""
    if cfg.latent == "gaussian":
        return jnp.sum(0.5 * math.log(2 * math.pi * math.e) + jnp.log(stats["std"]), -1)
    lp = stats["logits"]
    return -jnp.sum(jnp.exp(lp) * lp, (-2, -1))


def log_prob(cfg: WorldModelConfig, stats: dict[str, jax.Array], x: jax.Array) -> jax.Array:
    """``log p(x)`` of a flat sample ``x: [..., S]`` summed over the event -> ``[...]``."""
    if cfg.latent == "gaussian":
        z = (x - stats["mean"]) / stats["std"]
        return jnp.sum(-0.5 * z * z - jnp.log(stats["std"]) - 0.5 * math.log(2 * math.pi), -1)
    lp = stats["logits"]
    return jnp.sum(x.reshape(lp.shape) * lp, (-2, -1))


# --------------------------------------------------------------------------------------------
# RSSM steps
# --------------------------------------------------------------------------------------------


def initial_state(cfg: WorldModelConfig, batch: tuple[int, ...] = ()) -> RSSMState:
    """All-zero state ``[*batch, ...]`` (the reset state; its stats are a standard prior)."""
    if cfg.latent == "gaussian":
        stats = {"mean": jnp.zeros(batch + (cfg.stoch,)), "std": jnp.ones(batch + (cfg.stoch,))}
    else:
        shape = batch + (cfg.stoch, cfg.classes)
        stats = {"logits": jnp.full(shape, -math.log(cfg.classes), jnp.float32)}  # not weak-typed
    return RSSMState(
        deter=jnp.zeros(batch + (cfg.deter,)),
        stoch=jnp.zeros(batch + (stoch_size(cfg),)),
        stats=stats,
    )


def get_feat(state: RSSMState) -> jax.Array:
    """Dreamer feature ``f = [s, h]`` -> ``[..., F]``."""
    return jnp.concatenate([state.stoch, state.deter], -1)


# Dense layers applied inside the time scan. Their weight gradients are formed outside the scan
# (see :func:`_grads`): inside, they see stop-gradient weights plus a zero "tap" on their output.
RECURRENT = ("img_in", "gru", "obs_h", "obs_out")
Taps = dict[str, jax.Array]


def _add(x: jax.Array, taps: Taps | None, name: str) -> jax.Array:
    return x if taps is None else x + taps[name]


def _transition_io(
    cfg: WorldModelConfig,
    params: Params,
    stoch: jax.Array,
    deter: jax.Array,
    action: jax.Array,
    taps: Taps | None = None,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Deterministic part of the prior: ``h' = GRU(act(Dense([s, a])), h)`` -> ``[..., D]``,
    plus the inputs of its dense layers (``img_in: [..., S + A]``, ``gru: [..., hidden + D]``)."""
    mods = _rssm_nets(cfg)
    act = nets.ACTIVATIONS[cfg.act]
    x_in = jnp.concatenate([stoch, action], -1)
    x = act(_add(_apply(mods["img_in"], params["img_in"], x_in), taps, "img_in"))
    tap = None if taps is None else taps["gru"]
    h = _apply(mods["gru"], params["gru"], x, deter, tap)
    return h, {"img_in": x_in, "gru": jnp.concatenate([x, deter], -1)}


def _transition(
    cfg: WorldModelConfig, params: Params, stoch: jax.Array, deter: jax.Array, action: jax.Array
) -> jax.Array:
    """``h' = GRU(act(Dense([s, a])), h)`` -> ``[..., D]``."""
    return _transition_io(cfg, params, stoch, deter, action)[0]


def prior_stats(cfg: WorldModelConfig, params: Params, deter: jax.Array) -> dict[str, jax.Array]:
    """Prior ``p(s | h)`` statistics from ``deter: [..., D]`` (a function of ``h`` alone)."""
    return _stats(cfg, _apply(_rssm_nets(cfg)["img_out"], params["img_out"], deter))


def prior_mean(cfg: WorldModelConfig, params: Params, deter: jax.Array) -> jax.Array:
    """``m(h)``: prior mean (gaussian) or probabilities (categorical), flat ``[..., S]``."""
    return dist_mean(cfg, prior_stats(cfg, params, deter))


def _embed_proj(cfg: WorldModelConfig, params: Params, embed: jax.Array) -> jax.Array:
    """Embedding half of the posterior's first layer: ``[..., E] -> [..., hidden]``."""
    return _apply(_rssm_nets(cfg)["obs_e"], params["obs_e"], embed)


def _post_stats_io(
    cfg: WorldModelConfig,
    params: Params,
    deter: jax.Array,
    eproj: jax.Array,
    taps: Taps | None = None,
) -> tuple[dict[str, jax.Array], dict[str, jax.Array]]:
    """Posterior ``q(s | h, e)`` statistics ``Dense(act(Dense_h(h) + Dense_e(e)))``, plus the
    inputs of the two dense layers applied to ``h`` (``obs_h: [..., D]``, ``obs_out: [..., hidden]``)."""
    mods = _rssm_nets(cfg)
    act = nets.ACTIVATIONS[cfg.act]
    x = act(_add(_apply(mods["obs_h"], params["obs_h"], deter), taps, "obs_h") + eproj)
    raw = _add(_apply(mods["obs_out"], params["obs_out"], x), taps, "obs_out")
    return _stats(cfg, raw), {"obs_h": deter, "obs_out": x}


def _post_stats(
    cfg: WorldModelConfig, params: Params, deter: jax.Array, eproj: jax.Array
) -> dict[str, jax.Array]:
    return _post_stats_io(cfg, params, deter, eproj)[0]


def _reset(state: RSSMState, action: jax.Array, is_first: jax.Array) -> tuple[RSSMState, jax.Array]:
    """Zero the previous state and action where ``is_first: [...]`` is set."""
    keep = lambda x: jnp.where(
        is_first.reshape(is_first.shape + (1,) * (x.ndim - is_first.ndim)), 0, x
    )
    return state.replace(deter=keep(state.deter), stoch=keep(state.stoch)), keep(action)


def img_step(
    cfg: WorldModelConfig, params: Params, state: RSSMState, action: jax.Array, key: jax.Array
) -> RSSMState:
    """Stochastic prior step ``p(s', h' | s, h, a)``; state ``[..., ]``, action ``[..., A]``."""
    deter = _transition(cfg, params, state.stoch, state.deter, action)
    stats = prior_stats(cfg, params, deter)
    stoch = _sample(cfg, stats, _noise(cfg, key, deter.shape[:-1]))
    return RSSMState(deter=deter, stoch=stoch, stats=stats)


def img_step_mean(
    cfg: WorldModelConfig, params: Params, state: RSSMState, action: jax.Array
) -> RSSMState:
    """Deterministic prior step: ``s' = m(h')`` (LatCo's F_mu on the state pytree)."""
    deter = _transition(cfg, params, state.stoch, state.deter, action)
    stats = prior_stats(cfg, params, deter)
    return RSSMState(deter=deter, stoch=dist_mean(cfg, stats), stats=stats)


def obs_step(
    cfg: WorldModelConfig,
    params: Params,
    prev: RSSMState,
    prev_action: jax.Array,
    obs: jax.Array,
    is_first: jax.Array,
    key: jax.Array,
) -> tuple[RSSMState, RSSMState]:
    """One posterior filtering step (the agent's per-step verb).

    Args: prev ``[B]`` state; prev_action ``a_{t-1}: [B, A]``; obs ``o_t: [B, *obs_shape]`` raw;
    is_first ``[B]`` (resets prev state and action to zeros); key for this step.
    Returns (posterior, prior) at t, each ``[B]``. The batch may be empty (``()``).
    """
    prev, prev_action = _reset(prev, prev_action, is_first)
    deter = _transition(cfg, params, prev.stoch, prev.deter, prev_action)
    eproj = _embed_proj(cfg, params, encode(cfg, params, obs))
    post = _post_stats(cfg, params, deter, eproj)
    stoch = _sample(cfg, post, _noise(cfg, key, deter.shape[:-1]))
    prior = prior_stats(cfg, params, deter)
    prior_state = RSSMState(deter=deter, stoch=dist_mean(cfg, prior), stats=prior)
    return RSSMState(deter=deter, stoch=stoch, stats=post), prior_state


def _step_noise(cfg: WorldModelConfig, key: jax.Array, steps: int, batch: tuple[int, ...]):
    """Noise for ``steps`` consecutive steps, ``[steps, *batch, ...]``; step t uses
    ``split(key, steps)[t]`` exactly as the single-step verbs would."""
    return jax.vmap(lambda k: _noise(cfg, k, batch))(jax.random.split(key, steps))


def _time_major(x: jax.Array) -> jax.Array:
    return jnp.swapaxes(x, 0, 1)


def observe(
    cfg: WorldModelConfig,
    params: Params,
    obs: jax.Array,
    action: jax.Array,
    is_first: jax.Array,
    key: jax.Array,
    state: RSSMState | None = None,
    unroll: int | bool = 1,
) -> tuple[RSSMState, RSSMState]:
    """Posterior filtering over a sequence (``lax.scan`` over time).

    Args: obs ``[B, T, *obs_shape]``; action ``a_{t-1}: [B, T, A]``; is_first ``[B, T]``;
    key (step t uses ``split(key, T)[t]``, matching :func:`obs_step`); state: the state before
    step 0 (``[B]``; default zeros); unroll: scan unroll factor (static).
    Returns (posterior, prior), each ``[B, T]``; the prior's stoch is its mean.
    """
    post, prior, _ = _observe_io(cfg, params, obs, action, is_first, key, state, unroll)
    return post, prior


def _stop_dense(params: Params) -> Params:
    """Stop the gradient of the scanned dense layers' kernels and biases (they get theirs from
    the taps, :func:`_grads`); other parameters (e.g. the GRU's LayerNorm) are untouched."""
    out = dict(params)
    for name in RECURRENT:
        out[name] = {**params[name], "Dense_0": jax.lax.stop_gradient(params[name]["Dense_0"])}
    return out


def _observe_io(
    cfg: WorldModelConfig,
    params: Params,
    obs: jax.Array,
    action: jax.Array,
    is_first: jax.Array,
    key: jax.Array,
    state: RSSMState | None = None,
    unroll: int | bool = 1,
    taps: Taps | None = None,
) -> tuple[RSSMState, RSSMState, dict[str, jax.Array]]:
    """:func:`observe`, also returning the inputs of the scanned dense layers (time-major,
    ``[T, B, in]`` per name in :data:`RECURRENT`). With ``taps`` (``[T, B, out]`` zeros per name)
    those layers' weights are stop-gradient and the taps carry their output cotangents."""
    batch, steps = is_first.shape
    state = initial_state(cfg, (batch,)) if state is None else state
    eproj = _time_major(_embed_proj(cfg, params, encode(cfg, params, obs)))  # [T, B, hidden]
    first = _time_major(is_first)
    action = jnp.where(first[..., None], 0.0, _time_major(action).astype(jnp.float32))
    noise = _step_noise(cfg, key, steps, (batch,))
    rparams = params if taps is None else _stop_dense(params)

    def body(carry, xs):
        stoch, deter = carry
        a, ep, f, n, tap = xs
        stoch = jnp.where(f[:, None], 0.0, stoch)
        deter = jnp.where(f[:, None], 0.0, deter)
        deter, ins = _transition_io(cfg, rparams, stoch, deter, a, tap)
        stats, ins_post = _post_stats_io(cfg, rparams, deter, ep, tap)
        stoch = _sample(cfg, stats, n)
        return (stoch, deter), (stoch, deter, stats, {**ins, **ins_post})

    carry = (state.stoch, state.deter)
    xs = (action, eproj, first, noise, taps)
    _, (stoch, deter, stats, inputs) = jax.lax.scan(body, carry, xs, unroll=unroll)
    post = jax.tree.map(_time_major, RSSMState(deter=deter, stoch=stoch, stats=stats))
    prior = prior_stats(cfg, params, post.deter)
    prior_state = RSSMState(deter=post.deter, stoch=dist_mean(cfg, prior), stats=prior)
    return post, prior_state, inputs


def _batch_leading(state: RSSMState, batch_ndim: int) -> RSSMState:
    """``[T, *batch, ...] -> [*batch, T, ...]`` for every leaf."""
    return jax.tree.map(lambda x: jnp.moveaxis(x, 0, batch_ndim), state)


def imagine(
    cfg: WorldModelConfig,
    params: Params,
    start: RSSMState,
    actions: jax.Array,
    key: jax.Array,
) -> RSSMState:
    """Open-loop prior rollout from ``start [*batch]`` under ``actions: [*batch, H, A]``.

    Step k uses ``split(key, H)[k]`` exactly as :func:`img_step`. Returns states ``[*batch, H]``
    for k = 1..H (the start state is not included).
    """
    batch = start.deter.shape[:-1]
    horizon = actions.shape[-2]
    acts = jnp.moveaxis(actions, -2, 0)
    noise = _step_noise(cfg, key, horizon, batch)

    def body(state, xs):
        a, n = xs
        deter = _transition(cfg, params, state.stoch, state.deter, a)
        stats = prior_stats(cfg, params, deter)
        nxt = RSSMState(deter=deter, stoch=_sample(cfg, stats, n), stats=stats)
        return nxt, nxt

    _, states = jax.lax.scan(body, start, (acts, noise))
    return _batch_leading(states, len(batch))


def imagine_policy(
    cfg: WorldModelConfig,
    params: Params,
    start: RSSMState,
    policy: Callable[[jax.Array, jax.Array], jax.Array],
    horizon: int,
    key: jax.Array,
) -> tuple[RSSMState, jax.Array]:
    """Closed-loop prior rollout: ``a_k = policy(sg(f_k), key_k)``, then ``img_step``.

    Returns (states ``[*batch, H]`` for k = 1..H, actions ``[*batch, H, A]`` for k = 0..H-1).
    """
    batch = start.deter.shape[:-1]

    def body(state, k):
        kp, ks = jax.random.split(k)
        a = policy(jax.lax.stop_gradient(get_feat(state)), kp)
        nxt = img_step(cfg, params, state, a, ks)
        return nxt, (nxt, a)

    _, (states, acts) = jax.lax.scan(body, start, jax.random.split(key, horizon))
    return _batch_leading(states, len(batch)), jnp.moveaxis(acts, 0, len(batch))


# --------------------------------------------------------------------------------------------
# Loss
# --------------------------------------------------------------------------------------------


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
    """Inputs of the J_latent surrogate (ALGORITHM.md §4.5); pass to :func:`loss` when enabled.

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
    """World-model ELBO (ALGORITHM.md §1.4) on a replay batch.

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
    target = preprocess_obs(cfg, params, batch["obs"])
    sq_obs = jnp.square(decode(cfg, params, feat) - target)
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


# --------------------------------------------------------------------------------------------
# Optimisation
# --------------------------------------------------------------------------------------------


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


# --------------------------------------------------------------------------------------------
# Adapters for the planner and the Dreamer actor (protocols of pure, unbatched functions)
# --------------------------------------------------------------------------------------------


class PlanningFns(NamedTuple):
    """Latent-model protocol for planners; all functions unbatched (the caller vmaps).

    start(wm_params, ctx: RSSMState, a [A]) -> z1 [Z]: mean transition out of the filtered
      posterior state (uses its sample s_0);
    step(wm_params, z [Z], a [A]) -> z' [Z]: mean transition F_mu in plan space;
    reward(wm_params, z [Z]) -> []: predicted reward of arriving in z;
    feat(wm_params, z [Z]) -> [F]: Dreamer feature for value / actor heads;
    ctx_feat(wm_params, ctx) -> [F]: feature of a posterior state;
    step_reward(wm_params, z [Z], a [A]) -> (step(z, a), reward(z)): both in one pass (the reduced
      space computes the prior m(h) once for the two; ~15% of a collocation iteration);
    step_reward_feat(wm_params, z [Z], a [A]) -> (step(z, a), reward(z), feat(z)): the same pass
      with the features too, for planners that also read a value of ``feat(z)``;
    step_feat(wm_params, z [Z], a [A]) -> (step(z, a), feat(z)): the pass without the reward head,
      for rollouts that read the heads of all their states afterwards in one batched call;
    feat_reward(wm_params, f [F]) -> []: the reward head on features;
    size: Z.
    """

    start: Callable[[Params, RSSMState, jax.Array], jax.Array]
    step: Callable[[Params, jax.Array, jax.Array], jax.Array]
    reward: Callable[[Params, jax.Array], jax.Array]
    feat: Callable[[Params, jax.Array], jax.Array]
    ctx_feat: Callable[[Params, RSSMState], jax.Array]
    step_reward: Callable[[Params, jax.Array, jax.Array], tuple[jax.Array, jax.Array]]
    step_reward_feat: Callable[
        [Params, jax.Array, jax.Array], tuple[jax.Array, jax.Array, jax.Array]
    ]
    step_feat: Callable[[Params, jax.Array, jax.Array], tuple[jax.Array, jax.Array]]
    feat_reward: Callable[[Params, jax.Array], jax.Array]
    size: int


def planning_fns(cfg: WorldModelConfig, space: str) -> PlanningFns:
    """Plan-space adapter (ALGORITHM.md §3.2, §4.2).

    ``full``: z = [m, h] with m the stoch mean (gaussian mean / flat categorical probabilities),
    step = LatCo's ``F_mu = get_mean_feat(img_step(from_feat(z), a))`` (probabilities fed where
    samples would be). ``reduced``: z = h only, with ``s := m(h)``; exact at feasibility because
    the prior statistics are a function of h alone.
    """
    s_dim = stoch_size(cfg)

    def ctx_feat(p: Params, ctx: RSSMState) -> jax.Array:
        return get_feat(ctx)

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

        size = s_dim + cfg.deter
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

        size = cfg.deter
    else:
        raise ValueError(f"unknown collocation space {space!r}; valid: full, reduced")

    def rew(p: Params, z: jax.Array) -> jax.Array:
        return reward(cfg, p, feat(p, z))

    def feat_reward(p: Params, f: jax.Array) -> jax.Array:
        return reward(cfg, p, f)

    def step_reward_feat(
        p: Params, z: jax.Array, a: jax.Array
    ) -> tuple[jax.Array, jax.Array, jax.Array]:
        nz, f = step_feat(p, z, a)
        return nz, feat_reward(p, f), f

    def step_reward(p: Params, z: jax.Array, a: jax.Array) -> tuple[jax.Array, jax.Array]:
        nz, r, _ = step_reward_feat(p, z, a)
        return nz, r

    return PlanningFns(
        start=start,
        step=step,
        reward=rew,
        feat=feat,
        ctx_feat=ctx_feat,
        step_reward=step_reward,
        step_reward_feat=step_reward_feat,
        step_feat=step_feat,
        feat_reward=feat_reward,
        size=size,
    )


class ImagineFns(NamedTuple):
    """Pure per-state functions for imagination-based behaviour (the Dreamer actor).

    img_step(wm_params, state, a [..., A], key) -> state: stochastic prior step;
    get_feat(state) -> [..., F]; ctx_feat(wm_params, ctx) -> [F];
    reward(wm_params, feat [..., F]) -> [...]; initial(batch) -> zero state.
    """

    img_step: Callable[[Params, RSSMState, jax.Array, jax.Array], RSSMState]
    get_feat: Callable[[RSSMState], jax.Array]
    ctx_feat: Callable[[Params, RSSMState], jax.Array]
    reward: Callable[[Params, jax.Array], jax.Array]
    initial: Callable[[tuple[int, ...]], RSSMState]


def imagine_fns(cfg: WorldModelConfig) -> ImagineFns:
    return ImagineFns(
        img_step=lambda p, s, a, k: img_step(cfg, p, s, a, k),
        get_feat=get_feat,
        ctx_feat=lambda p, ctx: get_feat(ctx),
        reward=lambda p, f: reward(cfg, p, f),
        initial=lambda batch=(): initial_state(cfg, batch),
    )

"""Observation and reward heads of the world model: encoder/decoder (MLP for vectors, conv for
pixels), observation pre/post-processing, and the reward head (unit-variance MSE or DreamerV3's
symlog two-hot).

Pure functions over the world-model parameter pytree; the flax modules live in :mod:`mjx_collo.nets`.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from mjx_collo import nets
from mjx_collo.config import WorldModelConfig

Params = dict[str, Any]
PIXEL_NDIM = 3  # [H, W, C]


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


def is_pixel(params: Params) -> bool:
    """Whether these world-model parameters see pixels (a conv encoder) rather than vectors."""
    return "enc_conv" in params


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
    if is_pixel(params):
        return x / 255.0 - 0.5
    return symlog(x) if cfg.symlog_obs else x


def postprocess_obs(cfg: WorldModelConfig, params: Params, x: jax.Array) -> jax.Array:
    """Inverse of :func:`preprocess_obs` (decoder output -> raw observation units)."""
    if is_pixel(params):
        return (x + 0.5) * 255.0
    return symexp(x) if cfg.symlog_obs else x


def encode(cfg: WorldModelConfig, params: Params, obs: jax.Array) -> jax.Array:
    """``obs: [..., *obs_shape]`` raw -> embedding ``[..., E]``."""
    x = preprocess_obs(cfg, params, obs)
    if is_pixel(params):
        return _apply(nets.ConvEncoder(cfg.cnn_depth), params["enc_conv"], x)
    return _apply(nets.MLP(cfg.enc_layers, cfg.units, act=cfg.act), params["enc_mlp"], x)


def decode(cfg: WorldModelConfig, params: Params, feat: jax.Array) -> jax.Array:
    """``feat: [..., F]`` -> predicted observation mean in network space ``[..., *obs_shape]``."""
    if is_pixel(params):
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

"""The RSSM's stochastic-state distributions: diagonal Gaussian (Dreamer v1) or groups of
categoricals with unimix (DreamerV2), as statistics dicts (see :class:`~.rssm.RSSMState`).

Float config fields (``min_std``, ``unimix``) may be JAX tracers inside a swept program, so
nothing here branches on them in Python except a literal ``unimix == 0.0``.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from mjx_collo.config import WorldModelConfig


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

"""LatCo's constraint violations and log-multiplicative multiplier update (docs/ALGORITHM.md §3.4).

``lambda <- lambda * (1 + alpha * log10(viol / eps + eta))``, clamped to ``lam_clip``. With LC's
alpha = 0.1 and eta = 0.1 the factor lies in [0.9, ...), its fixed point is viol = (1 - eta) eps,
and multipliers never reach zero; the clamp keeps them positive for any constants.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def dyn_violation(d: jax.Array) -> jax.Array:
    """Per-step dynamics violation ||d_t||^2. d: [H, Z] -> [H]."""
    return jnp.sum(jnp.square(d), axis=-1)


def act_violation(a: jax.Array) -> jax.Array:
    """Per-step action-bound violation sum_d max(a^2 - 1, 0) (LC's metric). a: [H, A] -> [H]."""
    return jnp.sum(jnp.maximum(jnp.square(a) - 1.0, 0.0), axis=-1)


def act_hinge(a: jax.Array) -> jax.Array:
    """Action-bound residual max(|a| - 1, 0) (LC's residual). a: [H, A] -> [H, A]."""
    return jnp.maximum(jnp.abs(a) - 1.0, 0.0)


def update_multiplier(
    lam: jax.Array,
    viol: jax.Array,
    eps: jax.Array | float,
    alpha: jax.Array | float,
    eta: jax.Array | float,
    lo: jax.Array | float,
    hi: jax.Array | float,
) -> jax.Array:
    """One LatCo multiplier step. lam, viol: [H] -> [H], always in [lo, hi].

    A non-finite violation leaves its multiplier unchanged (NaN guard before the log).
    """
    ok = jnp.isfinite(viol)
    ratio = jnp.where(ok, viol, 0.0) / eps + eta
    factor = jnp.where(ok, 1.0 + alpha * jnp.log10(ratio), 1.0)
    new = jnp.clip(lam * factor, lo, hi)
    return jnp.where(jnp.isfinite(new), new, lam)


def kappa(
    lam: jax.Array, nu: jax.Array, dyn_scale: jax.Array | float, act_scale: jax.Array | float
) -> jax.Array:
    """LC's residual normalisation 1 / (mean sqrt(lam) s_d + mean sqrt(nu) s_a + 1). lam, nu: [H]."""
    return 1.0 / (jnp.mean(jnp.sqrt(lam)) * dyn_scale + jnp.mean(jnp.sqrt(nu)) * act_scale + 1.0)

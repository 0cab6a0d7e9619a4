"""Temporally correlated (colored) Gaussian noise for sampling-based planners.

White per-step samples explore action sequences that change every step; a motion that needs a
force held for many steps (a quadruped rolling off its back, docs/EXPERIMENTS.md) is then
astronomically unlikely among a planner's few samples. Power-law noise with spectrum ~ 1 / f^beta
along the time axis makes long, smooth pushes likely: beta 0 is white, 1 pink, 2 red. iCEM
(Pinneri et al., 2020) samples its CEM population this way (beta 2-2.5 on its tasks).

The generator is the Timmer & Koenig (1995) algorithm as the ``colorednoise`` package implements
it (``powerlaw_psd_gaussian``, the one iCEM uses), written in JAX so it runs inside the planner's
XLA program: random Fourier amplitudes scaled by f^(-beta/2) (the zero frequency at the lowest
nonzero one), inverse real FFT, divided by the exact standard deviation of an output step, so each
step has unit variance for every beta and length (``colorednoise``'s normalisation leaves out the
zero frequency: at the 15 steps of a plan its variance is ~7% too high for white noise, 19% for
beta 1, 33% for beta 2 and 38% for beta 2.5).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def colored_normal(key: jax.Array, shape: tuple[int, ...], beta) -> jax.Array:
    """Unit-variance Gaussian noise of ``shape`` ``(..., T, D)``, correlated along ``T`` with
    power spectrum ~ 1 / f^beta, independent across the other axes. ``beta`` may be traced (a
    swept hyperparameter)."""
    *lead, steps, dims = shape
    f = jnp.fft.rfftfreq(steps)
    scale = jnp.maximum(f, 1.0 / steps) ** (-jnp.asarray(beta, jnp.float32) / 2.0)
    # the standard deviation of each output step: frequency 0 (and Nyquist, for even T) carries
    # variance 2 s^2, every other frequency 4 s^2 (its conjugate pair), over T^2
    var = 4.0 * jnp.square(scale)
    var = var.at[0].multiply(0.5)
    if steps % 2 == 0:
        var = var.at[-1].multiply(0.5)
    sigma = jnp.sqrt(jnp.sum(var)) / steps
    k_re, k_im = jax.random.split(key)
    spec_shape = (*lead, dims, f.shape[0])
    re = jax.random.normal(k_re, spec_shape) * scale
    im = jax.random.normal(k_im, spec_shape) * scale
    # a real signal: no imaginary part at frequency 0 (and at the Nyquist frequency for even T)
    im = im.at[..., 0].set(0.0)
    re = re.at[..., 0].multiply(jnp.sqrt(2.0))
    if steps % 2 == 0:
        im = im.at[..., -1].set(0.0)
        re = re.at[..., -1].multiply(jnp.sqrt(2.0))
    y = jnp.fft.irfft(re + 1j * im, n=steps, axis=-1) / sigma
    return jnp.swapaxes(y, -1, -2).astype(jnp.float32)

"""Shooting baselines: CEM, MPPI (LatCo's ``shooting_cem``) and TD-MPC2-style ``mppi_value``.

docs/ALGORITHM.md §5. Each iteration samples ``samples`` action sequences from N(mean, std), clips them
to [-1, 1], rolls them out deterministically through the model and scores them by
``sum_k gamma^(k-1) r(z_k)`` (+ ``gamma^H V(z_H)`` for ``mppi_value``). Updates:

* ``cem``: mean/std of the top ``elites`` (std = sqrt(var + 1e-6), LC);
* ``mppi`` / ``mppi_value``: softmax(temperature * (score - max)) weights over the top ``elites``
  (LC's MPPI uses all samples as elites; TD-MPC2 uses 64 of 512), weighted mean and std;
* std is clamped to [min_std, max_std]. The plan returned is the mean.

``shooting.color`` > 0 draws the samples' noise correlated over the horizon (power spectrum
~ 1/f^color, :mod:`mjx_collo.noise`; iCEM); 0, the default, is white noise, drawn exactly as before.
``shooting.color_frac`` < 1 draws only that share of the samples colored and the rest white, so the
population holds both long pushes and step-by-step corrections and the elites pick between them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from mjx_collo import noise
from mjx_collo.config import Config
from mjx_collo.planners import objective as obj
from mjx_collo.planners.objective import Problem


@struct.dataclass
class ShootState:
    """Sampling distribution over action sequences. mean, std: [H, A]."""

    mean: jax.Array
    std: jax.Array


def init_shoot(cfg: Config, action_dim: int) -> ShootState:
    """Cold distribution: mean 0, std ``shooting.init_std`` clamped to [min_std, max_std]."""
    pc, sc = cfg.planner, cfg.planner.shooting
    shape = (pc.horizon, action_dim)
    std = jnp.clip(sc.init_std, sc.min_std, sc.max_std)
    return ShootState(mean=jnp.zeros(shape), std=jnp.full(shape, std, jnp.float32))


def shift_shoot(cfg: Config, prev: ShootState, shift: int) -> ShootState:
    """Warm start (TD-MPC2): mean shifted by ``shift`` steps with a zero tail; std reset."""
    horizon = prev.mean.shape[0]
    shift = min(shift, horizon)
    mean = jnp.concatenate([prev.mean[shift:], jnp.zeros_like(prev.mean[:shift])], axis=0)
    cold = init_shoot(cfg, prev.mean.shape[1])
    return ShootState(mean=mean, std=cold.std)


def sequence_return(prob: Problem, actions: jax.Array) -> jax.Array:
    """Objective of one action sequence [H, A] (deterministic rollout) -> []."""
    return obj.rollout_return(prob, actions)[0]


def _update(cfg: Config, samples: jax.Array, score: jax.Array) -> ShootState:
    """New distribution from samples [N, H, A] and scores [N]."""
    pc, sc = cfg.planner, cfg.planner.shooting
    top, idx = jax.lax.top_k(score, sc.elites)
    elite = samples[idx]
    if pc.kind == "cem":
        mean = jnp.mean(elite, axis=0)
        std = jnp.sqrt(jnp.var(elite, axis=0) + 1e-6)
    else:
        w = jax.nn.softmax(sc.temperature * (top - top[0]))
        mean = jnp.einsum("n,nha->ha", w, elite)
        std = jnp.sqrt(jnp.einsum("n,nha->ha", w, jnp.square(elite - mean)))
    return ShootState(mean=mean, std=jnp.clip(std, sc.min_std, sc.max_std))


def _sample_noise(sc, key: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """Standard-normal noise [samples, H, A]: white, colored (``color`` > 0), or the first
    ``round(samples * (1 - color_frac))`` white and the rest colored."""
    full = (sc.samples,) + tuple(shape)
    if isinstance(sc.color, float | int) and sc.color == 0:
        return jax.random.normal(key, full)
    colored = int(round(sc.samples * sc.color_frac))
    if colored >= sc.samples:
        return noise.colored_normal(key, full, sc.color)
    k_white, k_col = jax.random.split(key)
    white = jax.random.normal(k_white, (sc.samples - colored,) + tuple(shape))
    if colored == 0:
        return white
    red = noise.colored_normal(k_col, (colored,) + tuple(shape), sc.color)
    return jnp.concatenate([white, red], axis=0)


def optimize_shoot(
    cfg: Config,
    prob: Problem,
    state: ShootState,
    key: jax.Array,
    unroll: bool = False,
    first_means: jax.Array | None = None,
) -> tuple[ShootState, dict[str, jax.Array]]:
    """``shooting.iters`` sampling iterations (one ``fori_loop``) from ``state``.

    ``unroll`` unrolls the loop (only for FLOP counting: XLA counts a loop body once).
    ``first_means`` ``[samples, H, A]``: each sample's own centre in the first iteration (a mixed
    population, e.g. some samples around a policy prior's plan and the rest around zero); the
    elites then refit one distribution as usual.
    """
    sc = cfg.planner.shooting
    score_fn = jax.vmap(lambda acts: sequence_return(prob, acts))

    def body(k, st: ShootState) -> ShootState:
        eps = _sample_noise(sc, jax.random.fold_in(key, k), st.mean.shape)
        centre = st.mean if first_means is None else jnp.where(k == 0, first_means, st.mean)
        samples = jnp.clip(centre + st.std * eps, -1.0, 1.0)
        score = score_fn(samples)
        score = jnp.where(jnp.isfinite(score), score, -jnp.inf)
        return _update(cfg, samples, score)

    state = jax.lax.fori_loop(0, sc.iters, body, state, unroll=unroll)
    return state, shoot_metrics(prob, state)


def shoot_metrics(prob: Problem, state: ShootState) -> dict[str, jax.Array]:
    """Diagnostics of the mean plan (same keys as the collocation metrics; shooting plans are
    feasible by construction, so violations and multipliers are zero)."""
    acts = jnp.clip(state.mean, -1.0, 1.0)
    ret, r, _, v = obj.rollout_return(prob, acts)
    zero = jnp.zeros((), jnp.float32)
    return {
        "dyn_viol": zero,
        "dyn_viol_max": zero,
        "act_viol": zero,
        "lam_mean": zero,
        "lam_max": zero,
        "nu_mean": zero,
        "nu_max": zero,
        "plan_reward": jnp.mean(r),
        "plan_value": v,
        "plan_return": ret,
        "shadow_reward": jnp.mean(r),
        "shadow_return": ret,
        "feasible": jnp.ones((), jnp.float32),
        "iters_to_feasible": zero,
    }

"""Primal steps of the collocation planner (docs/ALGORITHM.md §3.3, Appendix B).

Every solver maps ``(problem, z, a, lam, nu, state)`` to the next ``(z, a, state)`` and returns the
dynamics residual ``d`` [H, Z] it evaluated at the *input* plan (reused for the multiplier update).
A step whose result is not finite is rejected (the plan stays where it was). The two Gauss-Newton
solvers return the raw residuals at the input (for LM step control and the multiplier update),
Adam returns the dynamics residual ``d`` [H, Z].

* :func:`gauss_newton_step` — exact LatCo: damped Gauss-Newton, normal matrix
  ``delta I + 2 J^T J`` assembled per block from per-pair Jacobians and solved by a block-tridiagonal
  Cholesky (``lax.scan``). Blocks are ``u_t = [a_{t-1}, z_t]``, t = 1..H, so the fixed context needs
  no pinning row.
* :func:`cg_step` — matrix-free Gauss-Newton: the same damped system solved by ``cg_iters``
  conjugate-gradient steps on ``J^T J v`` (one jvp + one vjp each, via ``linearize`` and
  ``linear_transpose``), never forming a Jacobian.
* :func:`adam_step` — first-order Adam on the exact Lagrangian (no softplus surrogate).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import optax
from jax.flatten_util import ravel_pytree
from jax.scipy.linalg import solve_triangular

from mjx_collo.planners import objective as obj
from mjx_collo.planners.objective import Problem, Raw


def _accept(new: jax.Array, old: jax.Array, ok: jax.Array) -> jax.Array:
    return jnp.where(ok, new, old)


def _finite(*xs: jax.Array) -> jax.Array:
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in xs]))


# ------------------------------------------------------------------------------------------------
# Exact Gauss-Newton (block-tridiagonal)
# ------------------------------------------------------------------------------------------------


def _pair_jacobians(
    prob: Problem, z: jax.Array, a: jax.Array
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Predictions and Jacobians of every transition.

    Returns:
      pred: [H, Z] predicted z_1..z_H; s_a: [H, Z, A] d pred_t / d a_{t-1}; s_z: [H-1, Z, Z]
      d pred_{t+1} / d z_t.
    """
    m, p = prob.model, prob.params

    def start(a0: jax.Array) -> tuple[jax.Array, jax.Array]:
        out = m.start(p, prob.ctx, a0)
        return out, out

    def step(zt: jax.Array, at: jax.Array) -> tuple[jax.Array, jax.Array]:
        out = m.step(p, zt, at)
        return out, out

    sa0, z1 = jax.jacfwd(start, has_aux=True)(a[0])
    (sz, sa), rest = jax.vmap(jax.jacfwd(step, argnums=(0, 1), has_aux=True))(z[:-1], a[1:])
    pred = jnp.concatenate([z1[None], rest], axis=0)
    return pred, jnp.concatenate([sa0[None], sa], axis=0), sz


def _normal_blocks(
    prob: Problem, z: jax.Array, a: jax.Array, w: obj.Weights
) -> tuple[jax.Array, jax.Array, jax.Array, Raw]:
    """Blocks of J^T J and J^T rho over u_t = [a_{t-1}, z_t].

    Returns:
      diag: [H, n, n]; off: [H-1, n, n] (block (t+1, t)); grad: [H, n] (n = A + Z); and the raw
      residuals at (z, a).
    """
    horizon, zdim = z.shape
    adim = a.shape[1]
    pred, s_a, s_z = _pair_jacobians(prob, z, a)
    d = z - pred
    c2 = jnp.square(w.dyn)  # [H]

    # Dynamics row t against its own block: c_t [-S_a | I].
    ata = jnp.einsum("hza,hzb->hab", s_a, s_a)
    eye = jnp.eye(zdim, dtype=z.dtype)
    top = jnp.concatenate([ata, -jnp.swapaxes(s_a, 1, 2)], axis=2)
    bot = jnp.concatenate([-s_a, jnp.broadcast_to(eye, (horizon, zdim, zdim))], axis=2)
    diag = c2[:, None, None] * jnp.concatenate([top, bot], axis=1)
    g_a = -jnp.einsum("hza,hz->ha", s_a, d)
    grad = c2[:, None] * jnp.concatenate([g_a, d], axis=1)

    # Dynamics row t+1 against the z part of block t: -c_{t+1} S_z.
    c2n = c2[1:]
    ztz = c2n[:, None, None] * jnp.einsum("hij,hik->hjk", s_z, s_z)
    diag = diag.at[:-1, adim:, adim:].add(ztz)
    grad = grad.at[:-1, adim:].add(-c2n[:, None] * jnp.einsum("hij,hi->hj", s_z, d[1:]))
    off_top = c2n[:, None, None] * jnp.einsum("hza,hzk->hak", s_a[1:], s_z)
    off_bot = -c2n[:, None, None] * s_z
    off = jnp.zeros((horizon - 1, adim + zdim, adim + zdim), z.dtype)
    off = off.at[:, :adim, adim:].set(off_top).at[:, adim:, adim:].set(off_bot)

    # Action-bound hinge rows: diagonal Jacobian c_a sign(a) 1[|a| > 1].
    hinge = jnp.maximum(jnp.abs(a) - 1.0, 0.0)
    s = jnp.sign(a) * (jnp.abs(a) > 1.0)
    ca2 = jnp.square(w.act)[:, None]
    idx = jnp.arange(adim)
    diag = diag.at[:, idx, idx].add(ca2 * jnp.square(s))
    grad = grad.at[:, :adim].add(ca2 * s * hinge)

    # Reward rows (scalar per block: one reverse-mode gradient each).
    q, gq = jax.vmap(jax.value_and_grad(obj.reward_residual, argnums=1), in_axes=(None, 0))(prob, z)
    gr = w.rew[:, None] * gq
    diag = diag.at[:, adim:, adim:].add(jnp.einsum("hi,hj->hij", gr, gr))
    grad = grad.at[:, adim:].add(gr * (w.rew * q)[:, None])

    # Value row on the last block.
    qv = jnp.zeros((), z.dtype)
    if prob.bootstrap:
        qv, gv = jax.value_and_grad(obj.value_residual, argnums=1)(prob, z[-1])
        gv = w.val * gv
        diag = diag.at[-1, adim:, adim:].add(jnp.outer(gv, gv))
        grad = grad.at[-1, adim:].add(gv * (w.val * qv))
    return diag, off, grad, Raw(d=d, hinge=hinge, rew=q, val=qv)


def block_tridiag_solve(diag: jax.Array, off: jax.Array, rhs: jax.Array) -> jax.Array:
    """Solve a symmetric positive-definite block-tridiagonal system by block Cholesky.

    Args:
      diag: [T, n, n] diagonal blocks; off: [T-1, n, n] sub-diagonal blocks (row t+1, col t);
      rhs: [T, n].
    Returns:
      x: [T, n].
    """
    l0 = jnp.linalg.cholesky(diag[0])
    y0 = solve_triangular(l0, rhs[0], lower=True)

    def fwd(carry, inp):
        l_prev, y_prev = carry
        d_k, off_k, r_k = inp
        c = solve_triangular(l_prev, off_k.T, lower=True).T  # off_k L_prev^{-T}
        l_k = jnp.linalg.cholesky(d_k - c @ c.T)
        y_k = solve_triangular(l_k, r_k - c @ y_prev, lower=True)
        return (l_k, y_k), (l_k, c, y_k)

    _, (ls, cs, ys) = jax.lax.scan(fwd, (l0, y0), (diag[1:], off, rhs[1:]))
    ls = jnp.concatenate([l0[None], ls], axis=0)
    ys = jnp.concatenate([y0[None], ys], axis=0)
    x_last = solve_triangular(ls[-1], ys[-1], lower=True, trans="T")

    def bwd(x_next, inp):
        l_k, c_next, y_k = inp
        x_k = solve_triangular(l_k, y_k - c_next.T @ x_next, lower=True, trans="T")
        return x_k, x_k

    _, xs = jax.lax.scan(bwd, x_last, (ls[:-1], cs, ys[:-1]), reverse=True)
    return jnp.concatenate([xs, x_last[None]], axis=0)


def gauss_newton_step(
    prob: Problem,
    z: jax.Array,
    a: jax.Array,
    w: obj.Weights,
    damping: Any,
) -> tuple[jax.Array, jax.Array, Raw]:
    """One damped GN step (delta I + 2 J^T J) dx = 2 J^T rho. z: [H, Z], a: [H, A].

    Returns (z', a', raw) with raw the unweighted residuals at the input plan.
    """
    adim = a.shape[1]
    diag, off, grad, raw = _normal_blocks(prob, z, a, w)
    n = diag.shape[-1]
    diag = damping * jnp.eye(n, dtype=z.dtype) + 2.0 * diag
    dx = block_tridiag_solve(diag, 2.0 * off, 2.0 * grad)
    ok = _finite(dx)
    return _accept(z - dx[:, adim:], z, ok), _accept(a - dx[:, :adim], a, ok), raw


# ------------------------------------------------------------------------------------------------
# Matrix-free Gauss-Newton (conjugate gradients)
# ------------------------------------------------------------------------------------------------


def _scale(raw: Raw, w: obj.Weights) -> Raw:
    return obj.weighted(raw, w)


def cg_step(
    prob: Problem,
    z: jax.Array,
    a: jax.Array,
    w: obj.Weights,
    damping: Any,
    iters: int,
    unroll: bool = False,
) -> tuple[jax.Array, jax.Array, Raw]:
    """One matrix-free damped GN step: ``iters`` CG steps on (J^T J + delta/2 I) dx = J^T rho.

    Same fixed point and damping as :func:`gauss_newton_step`. Returns (z', a', raw at input).
    """
    x0, unravel = ravel_pytree((z, a))

    def raw_fn(x: jax.Array) -> Raw:
        zz, aa = unravel(x)
        return obj.raw_residuals(prob, zz, aa)

    raw, jvp_raw = jax.linearize(raw_fn, x0)
    vjp_raw = jax.linear_transpose(jvp_raw, x0)
    rho = _scale(raw, w)
    mu = 0.5 * damping

    def normal(v: jax.Array) -> jax.Array:
        (out,) = vjp_raw(_scale(_scale(jvp_raw(v), w), w))
        return out + mu * v

    (b,) = vjp_raw(_scale(rho, w))
    dx = conjugate_gradient(normal, b, iters, unroll)
    ok = _finite(dx)
    dz, da = unravel(dx)
    return _accept(z - dz, z, ok), _accept(a - da, a, ok), raw


def conjugate_gradient(matvec, b: jax.Array, iters: int, unroll: bool = False) -> jax.Array:
    """``iters`` CG steps for ``matvec(x) = b`` from x = 0 (SPD matvec). b: [N] -> [N]."""
    tiny = jnp.finfo(b.dtype).tiny

    def body(_, carry):
        x, r, p, rr = carry
        ap = matvec(p)
        alpha = rr / jnp.maximum(jnp.vdot(p, ap), tiny)
        x = x + alpha * p
        r = r - alpha * ap
        rr_new = jnp.vdot(r, r)
        p = r + (rr_new / jnp.maximum(rr, tiny)) * p
        return x, r, p, rr_new

    x = jnp.zeros_like(b)
    x, *_ = jax.lax.fori_loop(0, iters, body, (x, b, b, jnp.vdot(b, b)), unroll=unroll)
    return x


# ------------------------------------------------------------------------------------------------
# First-order: Adam on the exact Lagrangian
# ------------------------------------------------------------------------------------------------


def adam_optimizer(lr: Any, decay: Any, b2: Any, iters: int) -> optax.GradientTransformation:
    """Adam whose step size decays geometrically from ``lr`` to ``lr * decay`` over ``iters``.

    ``b2`` should be short (0.9): the multipliers rescale the Lagrangian by orders of magnitude
    within one call, and with the usual 0.999 the stale second moment freezes coordinates (on the
    linear-quadratic probe 1000 iterations end 0.9 from the optimum with 0.999, exact with 0.9).
    """
    sched = lambda count: lr * jnp.power(decay, count / max(iters - 1, 1))
    return optax.adam(sched, b1=0.9, b2=b2)


def adam_step(
    prob: Problem,
    z: jax.Array,
    a: jax.Array,
    lam: jax.Array,
    nu: jax.Array,
    opt_state: optax.OptState,
    tx: optax.GradientTransformation,
) -> tuple[jax.Array, jax.Array, optax.OptState, jax.Array]:
    """One Adam step on the exact Lagrangian. Returns (z', a', opt_state', d)."""
    (_, raw), (gz, ga) = jax.value_and_grad(obj.lagrangian, argnums=(1, 2), has_aux=True)(
        prob, z, a, lam, nu
    )
    updates, new_state = tx.update((gz, ga), opt_state)
    nz, na = optax.apply_updates((z, a), updates)
    ok = _finite(nz, na)
    new_state = jax.tree.map(lambda n, o: _accept(n, o, ok), new_state, opt_state)
    return _accept(nz, z, ok), _accept(na, a, ok), new_state, raw.d

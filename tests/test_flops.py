"""Matmul FLOP counting (mjx_collo/flops.py): loops are counted as many times as they run, which
XLA's cost analysis does not do, so planning calls and chunks are not under-reported."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from test_planner import CTX, LQ

from mjx_collo import config
from mjx_collo.flops import matmul_flops
from mjx_collo.planner import make_planner

X = jnp.ones((8, 16))
W = jnp.ones((16, 4))
MM = 2 * 8 * 16 * 4  # one X @ W


def test_loop_free_matmuls_match_xla_cost_analysis():
    v = jnp.ones((4, 3))
    f = lambda x, w, v: (x @ w) @ v  # noqa: E731
    xla = jax.jit(f).lower(X, W, v).compile().cost_analysis()
    xla = xla[0] if isinstance(xla, list) else xla
    count = matmul_flops(f, X, W, v)
    assert count.exact
    assert count.flops == MM + 2 * 8 * 4 * 3 == xla["flops"]


def test_scan_and_fori_bodies_count_once_per_iteration_and_xla_counts_them_once():
    def scanned(x, w):
        return jax.lax.scan(lambda c, _: (c, c @ w), x, None, length=10)[1]

    assert matmul_flops(scanned, X, W).flops == 10 * MM
    xla = jax.jit(scanned).lower(X, W).compile().cost_analysis()
    xla = xla[0] if isinstance(xla, list) else xla
    assert xla["flops"] < 2 * MM  # the reason this module exists

    def nested(x, w):
        inner = lambda c: jax.lax.fori_loop(0, 3, lambda i, c: jnp.tanh(c @ w @ w.T), c)  # noqa: E731
        return jax.lax.scan(lambda c, _: (inner(c), None), x, None, length=5)[0]

    assert matmul_flops(nested, X, W).flops == 5 * 3 * 2 * MM


def test_gradients_and_vmap_are_counted():
    loss = lambda w: jnp.sum(jnp.tanh(X @ w))  # noqa: E731
    assert matmul_flops(loss, W).flops == MM
    assert matmul_flops(jax.grad(loss), W).flops == 2 * MM  # forward + d/dw (no d/dX)
    batched = jax.vmap(lambda x: x @ W)
    assert matmul_flops(batched, jnp.ones((7, 8, 16))).flops == 7 * MM


def test_cond_counts_the_dearer_branch_and_while_loops_once_and_says_so():
    def branchy(p, x, w):
        return jax.lax.cond(p, lambda x: (x @ w) @ w.T, lambda x: x, x)

    c = matmul_flops(branchy, True, X, W)
    assert c.flops == 2 * MM and c.branches == 1 and not c.exact

    def until(x, w):
        return jax.lax.while_loop(lambda c: jnp.sum(c) < 1e6, lambda c: c @ w @ w.T, x)

    c = matmul_flops(until, X, W)
    assert c.flops == 2 * MM and c.whiles == 1 and not c.exact


def test_convolution_flops():
    x = jnp.ones((2, 9, 9, 3))  # NHWC
    k = jnp.ones((4, 4, 3, 5))  # HWIO
    f = lambda x, k: jax.lax.conv_general_dilated(  # noqa: E731
        x, k, (2, 2), "VALID", dimension_numbers=("NHWC", "HWIO", "NHWC")
    )
    out = jax.eval_shape(f, x, k).shape  # [2, 3, 3, 5]
    assert matmul_flops(f, x, k).flops == 2 * np.prod(out) * 4 * 4 * 3
    # The input gradient of a strided conv (a transposed conv: input dilated by the stride) does
    # the conv's multiply-adds again, not stride^2 times them (the zeros it inserts are not work).
    # Forward + input gradient = 2 x forward, exactly; + kernel gradient = 3 x.
    conv = matmul_flops(f, x, k).flops
    grad_x = lambda x, k: jax.grad(lambda x: f(x, k).sum())(x)  # noqa: E731
    assert matmul_flops(grad_x, x, k).flops == 2 * conv
    grad_k = lambda x, k: jax.grad(lambda k: f(x, k).sum())(k)  # noqa: E731
    assert matmul_flops(grad_k, x, k).flops == 2 * conv
    same = lambda x, k: jax.lax.conv_general_dilated(  # noqa: E731  (padding is not work)
        x, k, (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC")
    )
    # SAME pads 1 before and 2 after: of 9 x 4 (position, tap) pairs per axis, 32 hit input
    assert matmul_flops(same, x, k).flops == 2 * 2 * 5 * 3 * 32**2


def _plan_flops(*overrides: str) -> float:
    cfg = config.load(
        method="collodreamer",
        overrides=["value.bootstrap=false", "planner.horizon=10", "planner.init=cem", *overrides],
    )
    planner = make_planner(cfg, LQ, 2)

    def call(k):
        return planner.optimize(None, CTX, planner.init(None, CTX, k), k)[0].a

    count = matmul_flops(call, jax.random.PRNGKey(0))
    assert count.exact
    return count.flops


def test_planning_call_counts_every_cem_rollout_step_and_every_iteration():
    """On the linear model z' = F z + G a (two 2x2 mat-vecs, 16 FLOPs per step), 20 more CEM
    samples cost 20 x iters x (H steps x 16 - 8) FLOPs: the start's F @ ctx is shared by all
    samples. Collocation iterations add a constant amount each."""
    cem = [
        _plan_flops(f"planner.init_cem.samples={s}", "planner.init_cem.iters=3")
        for s in (20, 40, 60)
    ]
    per_20 = 20 * 3 * (10 * 16 - 8)
    assert cem[1] - cem[0] == cem[2] - cem[1] == per_20
    iters = [_plan_flops("planner.init=rollout", f"planner.iters={k}") for k in (5, 10, 15)]
    assert iters[1] - iters[0] == iters[2] - iters[1] > 0

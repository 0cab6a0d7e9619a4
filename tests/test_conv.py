"""The pixel encoder/decoder's strided convolutions, computed as matmuls (``nets.StridedConv``;
XLA's CPU convolutions ran ~6x slower inside the training loop's while loop), give flax's
``nn.Conv`` / ``nn.ConvTranspose`` numbers, gradients and parameters, for every layer shape the
encoder and decoder use."""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjx_collo import nets

# (input size, in channels, out channels, kernel) of the depth-4 encoder and decoder layers
ENCODER = [(64, 3, 4, 4), (31, 4, 8, 4), (14, 8, 16, 4), (6, 16, 32, 4)]
DECODER = [(1, 128, 16, 5), (5, 16, 8, 5), (13, 8, 4, 6), (30, 4, 3, 6)]


def _both(flax_module, ours, size, cin):
    x = jax.random.normal(jax.random.key(0), (2, size, size, cin))
    params = flax_module.init(jax.random.key(1), x)["params"]
    params = jax.tree.map(lambda p: p + 0.1, params)  # a non-zero bias
    ref = lambda p, x: flax_module.apply({"params": p}, x)  # noqa: E731
    got = lambda p, x: ours.apply({"params": p}, x)  # noqa: E731
    assert jax.tree.map(jnp.shape, ours.init(jax.random.key(1), x)["params"]) == jax.tree.map(
        jnp.shape, params
    )
    return ref, got, params, x


def _check(ref, got, params, x):
    np.testing.assert_allclose(got(params, x), ref(params, x), rtol=1e-5, atol=1e-5)
    # gradients through a non-linear loss, to the parameters and to the input
    loss = lambda f: lambda p, x: jnp.sum(jnp.sin(f(p, x)))  # noqa: E731
    g_ref = jax.grad(loss(ref), argnums=(0, 1))(params, x)
    g_got = jax.grad(loss(got), argnums=(0, 1))(params, x)
    for a, b in zip(jax.tree.leaves(g_got), jax.tree.leaves(g_ref), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("size,cin,cout,k", ENCODER)
def test_strided_conv_is_flax_conv(size, cin, cout, k):
    flax_conv = nn.Conv(cout, (k, k), strides=(2, 2), padding="VALID")
    _check(*_both(flax_conv, nets.StridedConv(cout, k), size, cin))


@pytest.mark.parametrize("size,cin,cout,k", DECODER)
def test_strided_conv_transpose_is_flax_conv_transpose(size, cin, cout, k):
    flax_convt = nn.ConvTranspose(cout, (k, k), strides=(2, 2), padding="VALID")
    _check(*_both(flax_convt, nets.StridedConv(cout, k, transpose=True), size, cin))


def test_encoder_and_decoder_keep_flax_parameter_names_and_shapes():
    """Checkpoints and FLOP counts written with flax's layers read the same parameter tree."""
    enc = nets.ConvEncoder(depth=4).init(jax.random.key(0), jnp.zeros((1, 64, 64, 3)))["params"]
    dec = nets.ConvDecoder(3, depth=4).init(jax.random.key(0), jnp.zeros((1, 10)))["params"]
    assert sorted(enc) == [f"Conv_{i}" for i in range(4)]
    assert sorted(dec) == [
        "ConvTranspose_0",
        "ConvTranspose_1",
        "ConvTranspose_2",
        "ConvTranspose_3",
        "Dense_0",
    ]
    assert enc["Conv_0"]["kernel"].shape == (4, 4, 3, 4)
    assert dec["ConvTranspose_3"]["kernel"].shape == (6, 6, 4, 3)
    out = nets.ConvDecoder(3, depth=4).apply({"params": dec}, jnp.zeros((2, 5, 10)))
    assert out.shape == (2, 5, 64, 64, 3)

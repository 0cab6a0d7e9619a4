"""Flax network modules. The only place flax layers are defined (DESIGN rule 7).

Everything outside this file sees ``init``/``apply`` pure functions and parameter pytrees.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import flax.linen as nn
import jax
import jax.numpy as jnp

ACTIVATIONS: dict[str, Callable[[jax.Array], jax.Array]] = {
    "elu": nn.elu,
    "silu": nn.silu,
    "relu": nn.relu,
    "tanh": jnp.tanh,
}


class MLP(nn.Module):
    """Dense stack ``[..., in] -> [..., out]``.

    Attributes:
      layers: number of hidden layers; units: hidden width; out: output width (None = no head).
      norm: "none" | "layer" | "batch" applied before each activation (batch uses
        ``use_running_average=not train``).
      dropout: rate after each hidden activation, active only when ``train=True``.
    """

    layers: int
    units: int
    out: int | None = None
    act: str = "elu"
    norm: str = "none"
    dropout: float = 0.0

    @nn.compact
    def __call__(self, x: jax.Array, train: bool = False) -> jax.Array:
        act = ACTIVATIONS[self.act]
        for i in range(self.layers):
            x = nn.Dense(self.units)(x)
            if self.norm == "layer":
                x = nn.LayerNorm()(x)
            elif self.norm == "batch":
                x = nn.BatchNorm(use_running_average=not train)(x)
            x = act(x)
            # A literal 0.0 adds no layer; a traced rate (a swept value.dropout) always does.
            if not (isinstance(self.dropout, int | float) and self.dropout == 0.0):
                x = SweepableDropout(self.dropout, deterministic=not train, name=f"Dropout_{i}")(x)
        if self.out is not None:
            x = nn.Dense(self.out)(x)
        return x


class SweepableDropout(nn.Dropout):
    """``nn.Dropout`` whose rate may be a JAX tracer (a swept hyperparameter): the same mask and
    scaling, without flax's Python checks of the rate (``rate == 0.0``), which a tracer cannot
    answer. Named like flax's own dropout layers, so it draws the same masks. Rates must be < 1
    (the config checks it)."""

    @nn.compact
    def __call__(self, inputs: jax.Array, deterministic: bool | None = None) -> jax.Array:
        deterministic = nn.merge_param("deterministic", self.deterministic, deterministic)
        if deterministic:
            return inputs
        keep_prob = 1.0 - self.rate
        rng = self.make_rng(self.rng_collection)
        mask = jax.random.bernoulli(rng, p=keep_prob, shape=inputs.shape)
        return jax.lax.select(mask, inputs / keep_prob, jnp.zeros_like(inputs))


class Linear(nn.Module):
    """One dense layer ``[..., in] -> [..., out]`` (optionally without bias)."""

    out: int
    bias: bool = True

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        return nn.Dense(self.out, use_bias=self.bias)(x)


class GRUCell(nn.Module):
    """DreamerV2 GRU cell (``dreamerv2/common/nets.py::GRUCell``), plain or layer-normed.

    ``parts = [LayerNorm](Dense_{3*units}([x, h]))``; ``reset, cand, update = split(parts)``;
    ``cand = tanh(sigmoid(reset) * cand)``; ``update = sigmoid(update - 1)``;
    ``h' = update * cand + (1 - update) * h``. One fused matmul per step.

    Call: ``(x: [..., X], h: [..., units], tap=None) -> h': [..., units]``. ``tap`` (optional,
    ``[..., 3 * units]``) is added to the dense output before the norm: a zero tap whose gradient
    is the dense layer's output cotangent (used to batch weight gradients outside a time scan).
    """

    units: int
    layernorm: bool = True
    update_bias: float = -1.0

    @nn.compact
    def __call__(self, x: jax.Array, h: jax.Array, tap: jax.Array | None = None) -> jax.Array:
        parts = nn.Dense(3 * self.units)(jnp.concatenate([x, h], -1))
        if tap is not None:
            parts = parts + tap
        if self.layernorm:
            parts = nn.LayerNorm()(parts)
        reset, cand, update = jnp.split(parts, 3, axis=-1)
        cand = jnp.tanh(nn.sigmoid(reset) * cand)
        update = nn.sigmoid(update + self.update_bias)
        return update * cand + (1.0 - update) * h


def _flatten_batch(x: jax.Array, event_ndim: int) -> tuple[jax.Array, tuple[int, ...]]:
    """``[*batch, *event] -> ([prod(batch), *event], batch)``."""
    batch = x.shape[: x.ndim - event_ndim]
    return x.reshape((-1,) + x.shape[x.ndim - event_ndim :]), batch


def conv_stride2(x: jax.Array, kernel: jax.Array, bias: jax.Array) -> jax.Array:
    """``nn.Conv(strides=2, padding="VALID")`` as one matmul on patches: ``x [B, H, W, C]``,
    ``kernel [k, k, C, O]`` -> ``[B, (H - k) // 2 + 1, (W - k) // 2 + 1, O]``.

    Why not ``lax.conv``: XLA's CPU convolutions inside a while loop (the training loop's
    ``fori_loop`` of updates) ran ~6x slower than the same convolution outside one (a pixel
    world-model update at depth 8: 9.7 s vs 1.5 s on 2 cores); strided slices, a concatenation
    and a dot stay fast in loops and under ``vmap`` over seeds, forward and backward
    (docs/BENCHMARKS.md "Pixels"). The same numbers as ``nn.Conv`` up to float rounding.
    """
    k = kernel.shape[0]
    b, h, w, c = x.shape
    ho, wo = (h - k) // 2 + 1, (w - k) // 2 + 1
    cols = [
        x[:, i : i + 2 * ho - 1 : 2, j : j + 2 * wo - 1 : 2, :] for i in range(k) for j in range(k)
    ]
    patches = jnp.concatenate(cols, axis=-1)  # [B, Ho, Wo, k*k*C], ordered (i, j, c)
    return patches @ kernel.reshape(k * k * c, -1) + bias


def conv_transpose_stride2(x: jax.Array, kernel: jax.Array, bias: jax.Array) -> jax.Array:
    """``nn.ConvTranspose(strides=2, padding="VALID")`` (``transpose_kernel=False``) as one
    matmul on patches: ``x [B, H, W, C]``, ``kernel [k, k, C, O]`` ->
    ``[B, 2 (H - 1) + k, 2 (W - 1) + k, O]``. Why: see :func:`conv_stride2`.

    Input pixel ``i`` adds ``x[i] @ kernel[k - 1 - a]`` to output ``2 i + a``. Splitting the tap
    ``a = 2 p + q`` (the kernel padded to even size 2P), output ``2 m + q`` is the sum over
    ``p < P`` of ``x[m - p]`` times tap ``2 p + q``: a stride-1 convolution of the zero-padded
    input whose 4 O output channels are the four output parities ("sub-pixel" convolution), one
    matmul of the P x P patches, then the parities interleave. A 1 x 1 input is one matmul."""
    k = kernel.shape[0]
    b, h, w, c = x.shape
    o = kernel.shape[-1]
    flipped = kernel[::-1, ::-1]  # output 2 i + a takes flipped[a]
    if h == 1 and w == 1:
        taps = flipped.transpose(2, 0, 1, 3).reshape(c, k * k * o)
        return (x.reshape(b, c) @ taps).reshape(b, k, k, o) + bias
    if k % 2:  # an extra zero tap makes both parities the same length
        flipped = jnp.pad(flipped, ((0, 1), (0, 1), (0, 0), (0, 0)))
    half = flipped.shape[0] // 2
    # weights[(p, r, c), (q, qc, o)] = flipped[2 p + q, 2 r + qc, c, o]
    weights = flipped.reshape(half, 2, half, 2, c, o).transpose(0, 2, 4, 1, 3, 5)
    weights = weights.reshape(half * half * c, 4 * o)
    rows, cols = h - 1 + half, w - 1 + half
    pad = half - 1
    xp = jnp.pad(x, ((0, 0), (pad, pad), (pad, pad), (0, 0)))
    patches = jnp.concatenate(
        [
            xp[:, pad - p : pad - p + rows, pad - r : pad - r + cols, :]  # x[m - p, n - r]
            for p in range(half)
            for r in range(half)
        ],
        axis=-1,
    )
    y = (patches @ weights).reshape(b, rows, cols, 2, 2, o)
    out = y.transpose(0, 1, 3, 2, 4, 5).reshape(b, 2 * rows, 2 * cols, o)
    return out[:, : 2 * (h - 1) + k, : 2 * (w - 1) + k] + bias


class StridedConv(nn.Module):
    """Stride-2 VALID convolution (``transpose=False``) or transposed convolution, computed by
    :func:`conv_stride2` / :func:`conv_transpose_stride2`. Parameters as flax's ``nn.Conv`` /
    ``nn.ConvTranspose`` (``kernel [k, k, C, O]`` LeCun normal, ``bias [O]`` zeros), so a
    module named like flax's own (``Conv_0``, ``ConvTranspose_0``) has the same parameters."""

    features: int
    kernel_size: int
    transpose: bool = False

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        k = self.kernel_size
        kernel = self.param(
            "kernel", nn.initializers.lecun_normal(), (k, k, x.shape[-1], self.features)
        )
        bias = self.param("bias", nn.initializers.zeros, (self.features,))
        fn = conv_transpose_stride2 if self.transpose else conv_stride2
        return fn(x, kernel, bias)


class ConvEncoder(nn.Module):
    """D1/LC pixel encoder: 4 x Conv(k4, s2, VALID), depths d, 2d, 4d, 8d; act between.

    Call: ``img: [..., 64, 64, C] float (already preprocessed) -> [..., 32 * depth]``
    (2 x 2 x 8d flattened; 1024 for depth 32). Layers are :class:`StridedConv` (matmuls).
    """

    depth: int = 32
    act: str = "relu"

    @nn.compact
    def __call__(self, img: jax.Array) -> jax.Array:
        x, batch = _flatten_batch(img, 3)
        act = ACTIVATIONS[self.act]
        for i in range(4):
            x = act(StridedConv(self.depth * 2**i, 4, name=f"Conv_{i}")(x))
        return x.reshape(batch + (-1,))


class ConvDecoder(nn.Module):
    """D1/LC pixel decoder: Dense(32 d) -> 1x1 -> ConvT(4d, k5) -> ConvT(2d, k5) -> ConvT(d, k6)
    -> ConvT(C, k6), stride 2, VALID; spatial 1 -> 5 -> 13 -> 30 -> 64.

    Call: ``feat: [..., F] -> mean image [..., 64, 64, channels]``. Layers are
    :class:`StridedConv` (matmuls).
    """

    channels: int = 3
    depth: int = 32
    act: str = "relu"

    @nn.compact
    def __call__(self, feat: jax.Array) -> jax.Array:
        x, batch = _flatten_batch(feat, 1)
        act = ACTIVATIONS[self.act]
        x = nn.Dense(32 * self.depth)(x).reshape((-1, 1, 1, 32 * self.depth))
        layers = ((4 * self.depth, 5), (2 * self.depth, 5), (self.depth, 6), (self.channels, 6))
        for i, (features, kernel) in enumerate(layers):
            x = StridedConv(features, kernel, transpose=True, name=f"ConvTranspose_{i}")(x)
            if i < len(layers) - 1:
                x = act(x)
        return x.reshape(batch + x.shape[1:])


def init_params(module: nn.Module, key: jax.Array, *args: jax.Array) -> dict:
    """``module.init(key, *args)["params"]`` with flax's default distributions, drawn in one call.

    Kernels: LeCun truncated normal (variance 1/fan_in, fan_in = prod(kernel.shape[:-1])); biases
    zero; LayerNorm scales one. Equivalent in distribution to flax's defaults (the random stream
    differs) but one RNG op instead of one per layer: XLA's CPU compile time grows by ~0.3 s per
    RNG op, which dominated model init. ``args`` may be ``jax.ShapeDtypeStruct``s.
    """
    return init_many({"m": (module, args)}, key)["m"]


def init_many(specs: dict[str, tuple[nn.Module, tuple]], key: jax.Array) -> dict:
    """:func:`init_params` for several modules ``{name: (module, args)}`` with one RNG draw."""
    shapes = {
        name: jax.eval_shape(lambda a, m=m: m.init(key, *a)["params"], args)
        for name, (m, args) in specs.items()
    }
    leaves, treedef = jax.tree_util.tree_flatten_with_path(shapes)
    sizes = [math.prod(s.shape) if _leaf_name(path) == "kernel" else 0 for path, s in leaves]
    # Truncated to [-2, 2] std; 0.8796 corrects the std of the truncated unit normal.
    flat = jax.random.truncated_normal(key, -2.0, 2.0, (max(sum(sizes), 1),)) / 0.87962566
    out, offset = [], 0
    for (path, s), n in zip(leaves, sizes, strict=True):
        name = _leaf_name(path)
        if name == "kernel":
            fan_in = math.prod(s.shape[:-1])
            out.append(flat[offset : offset + n].reshape(s.shape) / math.sqrt(fan_in))
            offset += n
        elif name == "scale":
            out.append(jnp.ones(s.shape, s.dtype))
        elif name == "bias":
            out.append(jnp.zeros(s.shape, s.dtype))
        else:
            raise ValueError(f"init_params: no default initializer for parameter {path}")
    return jax.tree_util.tree_unflatten(treedef, out)


def _leaf_name(path: tuple) -> str:
    return str(getattr(path[-1], "key", path[-1]))

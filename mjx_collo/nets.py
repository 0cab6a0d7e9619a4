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


class ConvEncoder(nn.Module):
    """D1/LC pixel encoder: 4 x Conv(k4, s2, VALID), depths d, 2d, 4d, 8d; act between.

    Call: ``img: [..., 64, 64, C] float (already preprocessed) -> [..., 32 * depth]``
    (2 x 2 x 8d flattened; 1024 for depth 32).
    """

    depth: int = 32
    act: str = "relu"

    @nn.compact
    def __call__(self, img: jax.Array) -> jax.Array:
        x, batch = _flatten_batch(img, 3)
        act = ACTIVATIONS[self.act]
        for i in range(4):
            x = act(nn.Conv(self.depth * 2**i, (4, 4), strides=(2, 2), padding="VALID")(x))
        return x.reshape(batch + (-1,))


class ConvDecoder(nn.Module):
    """D1/LC pixel decoder: Dense(32 d) -> 1x1 -> ConvT(4d, k5) -> ConvT(2d, k5) -> ConvT(d, k6)
    -> ConvT(C, k6), stride 2, VALID; spatial 1 -> 5 -> 13 -> 30 -> 64.

    Call: ``feat: [..., F] -> mean image [..., 64, 64, channels]``.
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
            x = nn.ConvTranspose(features, (kernel, kernel), strides=(2, 2), padding="VALID")(x)
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

"""Flax network modules. The only place flax layers are defined (DESIGN rule 7).

Everything outside this file sees ``init``/``apply`` pure functions and parameter pytrees.
"""

from __future__ import annotations

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
        for _ in range(self.layers):
            x = nn.Dense(self.units)(x)
            if self.norm == "layer":
                x = nn.LayerNorm()(x)
            elif self.norm == "batch":
                x = nn.BatchNorm(use_running_average=not train)(x)
            x = act(x)
            if self.dropout > 0.0:
                x = nn.Dropout(self.dropout, deterministic=not train)(x)
        if self.out is not None:
            x = nn.Dense(self.out)(x)
        return x

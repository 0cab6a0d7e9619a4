"""Pixel world model, layer by layer: ms per forward + backward of each encoder and decoder layer
(``nets.conv_stride2`` / ``nets.conv_transpose_stride2``) on one update's frames, and the bytes of
the patch tensor each one builds.

Timed the way the trainer runs them: inside a ``fori_loop`` (the learner's loop of updates), on
new frames every iteration (uint8 frames converted as the world model does, so nothing is hoisted
out of the loop), gradients for the kernel and for the layer's input except at the first encoder
layer (whose input is data). Answers "where does a pixel update's time go" when a layer changes.
Prints a table and writes ``bench_results/conv_layers.json``.

    python benchmarks/bench_conv.py
    python benchmarks/bench_conv.py --depth 32 --batch 800
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path


def parse() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--depth", type=int, default=8, help="wm.cnn_depth")
    p.add_argument(
        "--batch", type=int, default=800, help="frames per update (replay batch x length)"
    )
    p.add_argument("--iters", type=int, default=10, help="loop iterations per timed call")
    p.add_argument("--repeats", type=int, default=3, help="timed calls (best is reported)")
    p.add_argument("--out", default="bench_results/conv_layers.json")
    return p.parse_args()


def layers(depth: int) -> list[dict]:
    """The encoder's and decoder's layers: input shape, output channels, kernel, kind."""
    d = depth
    enc = [((64, 64, 3), d), ((31, 31, d), 2 * d), ((14, 14, 2 * d), 4 * d), ((6, 6, 4 * d), 8 * d)]
    dec = [((1, 1, 32 * d), 4 * d, 5), ((5, 5, 4 * d), 2 * d, 5), ((13, 13, 2 * d), d, 5 + 1)]
    dec += [((30, 30, d), 3, 6)]
    out = [
        {"name": f"Conv_{i}", "input": s, "features": o, "kernel": 4, "transpose": False}
        for i, (s, o) in enumerate(enc)
    ]
    out += [
        {"name": f"ConvTranspose_{i}", "input": s, "features": o, "kernel": k, "transpose": True}
        for i, (s, o, k) in enumerate(dec)
    ]
    return out


def measure(layer: dict, batch: int, iters: int, repeats: int) -> dict:
    import jax
    import jax.numpy as jnp

    from mjx_collo import nets

    fn = nets.conv_transpose_stride2 if layer["transpose"] else nets.conv_stride2
    shape, o, k = tuple(layer["input"]), layer["features"], layer["kernel"]
    first = layer["name"] == "Conv_0"
    keys = jax.random.split(jax.random.key(0), 3)
    frames = jax.random.randint(keys[0], (iters, batch) + shape, 0, 256).astype(jnp.uint8)
    w = 0.1 * jax.random.normal(keys[1], (k, k, shape[-1], o))
    b = jnp.zeros((o,))
    y_shape = jax.eval_shape(fn, jax.ShapeDtypeStruct((batch,) + shape, jnp.float32), w, b).shape
    g = jax.random.normal(keys[2], y_shape)

    def body(i, carry):
        w, acc = carry
        x = frames[i].astype(jnp.float32) / 255.0 - 0.5

        def loss(x, w):
            return jnp.sum(jax.nn.relu(fn(x, w, b)) * g)

        if first:
            gw = jax.grad(loss, argnums=1)(x, w)
            return w - 1e-6 * gw, acc
        gx, gw = jax.grad(loss, argnums=(0, 1))(x, w)
        return w - 1e-6 * gw, acc + gx.sum()

    run = jax.jit(lambda w: jax.lax.fori_loop(0, iters, body, (w, jnp.zeros(()))))
    jax.block_until_ready(run(w))
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(run(w))
        best = min(best, (time.perf_counter() - t) / iters)
    if layer["transpose"] and shape[0] > 1:
        half = (k + 1) // 2
        patch = batch * (shape[0] - 1 + half) * (shape[1] - 1 + half) * half * half * shape[-1]
    elif layer["transpose"]:
        patch = 0
    else:
        patch = batch * y_shape[1] * y_shape[2] * k * k * shape[-1]
    return {
        **layer,
        "output": list(y_shape[1:]),
        "ms": 1e3 * best,
        "patch_mib": 4 * patch / 2**20,
        "input_grad": not first,
    }


def main() -> None:
    args = parse()
    import jax

    rows = [measure(layer, args.batch, args.iters, args.repeats) for layer in layers(args.depth)]
    total = sum(r["ms"] for r in rows)
    print(f"depth {args.depth}, {args.batch} frames, forward + backward in a fori_loop:")
    print(f"{'layer':18s} {'input':>14s} {'output':>14s} {'patches':>10s} {'ms':>7s} {'share':>6s}")
    for r in rows:
        print(
            f"{r['name']:18s} {str(tuple(r['input'])):>14s} {str(tuple(r['output'])):>14s} "
            f"{r['patch_mib']:8.0f}Mi {r['ms']:7.1f} {r['ms'] / total:6.0%}"
        )
    print(f"{'all layers':18s} {'':>14s} {'':>14s} {'':>10s} {total:7.1f}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(
        json.dumps(
            {
                "depth": args.depth,
                "batch": args.batch,
                "layers": rows,
                "total_ms": total,
                "machine": {"cpu": platform.processor(), "devices": len(jax.devices())},
                "jax": jax.__version__,
            },
            indent=2,
        )
        + "\n"
    )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

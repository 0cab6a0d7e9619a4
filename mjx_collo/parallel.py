"""Seeds, sweeps and devices: the seed axis of a run.

A run's seeds (and swept float hyperparameters) are an outer ``vmap`` over the one-seed program
of :mod:`mjx_collo.trainer`; on several devices the seed axis is sharded with ``shard_map``, each
device running its own block of seeds. Seeds never communicate.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

from mjx_collo.config import Config, ConfigError
from mjx_collo.trainer import Trainer


def seed_keys(cfg: Config, num_seeds: int, first: int = 0) -> jax.Array:
    """Independent keys for seeds ``first .. first + num_seeds - 1`` from ``run.seed`` ([S, 2]).

    Seed i has the same key whichever program trains it, so seeds 2-3 trained alone
    (``--first-seed 2``) are the seeds 2-3 of a vmapped ``--seeds 4`` run."""
    base = jax.random.PRNGKey(cfg.run.seed)
    return jax.vmap(lambda i: jax.random.fold_in(base, i))(first + jnp.arange(num_seeds))


def first_seed(labels: list[dict]) -> int:
    """The first seed index of a run's labels (``seeds.json``, checkpoint metadata): 0 for a
    sweep, whose keys follow the run index."""
    if not labels or any(set(lab) - {"seed"} for lab in labels):
        return 0
    return int(labels[0].get("seed", 0))


def check_first_seed(first: int, sweep: dict | str | None) -> None:
    """ConfigError unless ``first`` is a seed index >= 0 of a run without a sweep (a sweep's runs
    are keyed by their place in the grid, so its seeds train together)."""
    if first < 0 or (first and sweep):
        raise ConfigError(
            f"--first-seed {first}: give a seed index >= 0, and no --sweep (a sweep's runs are "
            "keyed by their place in the grid, so its seeds train together)"
        )


def sweep_grid(
    sweep: dict[str, list[float]], seeds: int, first: int = 0
) -> tuple[int, dict[str, jax.Array], list[dict[str, float]]]:
    """Cartesian product of swept values x seeds -> (S total, hyper {key: [S]}, per-run labels).

    A key ``a+b`` (``config.parse_sweep``) is one axis whose values both keys take together.
    ``first``: the seeds are ``first .. first + seeds - 1`` (not with a sweep)."""
    check_first_seed(first, sweep)
    combos: list[dict[str, float]] = [{}]
    for k in sorted(sweep):
        combos = [{**c, **dict.fromkeys(k.split("+"), v)} for c in combos for v in sweep[k]]
    labels = [dict(c, seed=first + i) for c in combos for i in range(seeds)]
    keys = sorted(p for k in sweep for p in k.split("+"))
    hyper = {k: jnp.asarray([lab[k] for lab in labels], jnp.float32) for k in keys}
    return len(labels), hyper, labels


def mesh_sharding(num_seeds: int):
    """NamedSharding of the seed axis over all devices (None if 1 device or not divisible)."""
    devices = jax.devices()
    if jax.process_count() > 1 and num_seeds % len(devices):
        raise ConfigError(
            f"{num_seeds} run(s) cannot be split over the {len(devices)} devices of "
            f"{jax.process_count()} processes: use a multiple of {len(devices)} seeds x sweep values"
        )
    if len(devices) < 2 or num_seeds % len(devices):
        return None
    import numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    mesh = Mesh(np.array(devices), ("seed",))
    return NamedSharding(mesh, PartitionSpec("seed"))


def replicated(sharding):
    """The same mesh as ``sharding`` with every array replicated (schedule counters)."""
    return jax.sharding.NamedSharding(sharding.mesh, jax.sharding.PartitionSpec())


def over_seeds(f: Callable, in_axes: tuple[int | None, ...]) -> Callable:
    """``vmap(f, in_axes)`` over the seed axis, except that one seed runs unbatched.

    With a seed axis of size 1, vmap turns every matmul against the seed's weights into a
    batched dot, which XLA's CPU backend runs markedly slower than the plain one (figures in
    docs/BENCHMARKS.md, "Seed axis"). One seed is the common case (``make train``), so this drops the axis, calls ``f`` directly and puts the axis
    back (reshapes only).
    """
    vf = jax.vmap(f, in_axes=in_axes)

    def g(*args):
        sizes = {
            x.shape[0]
            for a, ax in zip(args, in_axes, strict=True)
            if ax == 0
            for x in jax.tree.leaves(a)
        }
        if sizes != {1}:
            return vf(*args)
        pairs = zip(args, in_axes, strict=True)
        one = [jax.tree.map(lambda x: x[0], a) if ax == 0 else a for a, ax in pairs]
        return jax.tree.map(lambda x: x[None], f(*one))

    return g


def batched(trainer: Trainer, sharding=None):
    """jit(vmap) of init / chunk / evaluate over the seed axis (state donated into chunk).

    With a seed sharding the functions run under ``shard_map``: each device runs its own block of
    seeds through :func:`over_seeds`, so a device holding one seed runs it unbatched. Seeds never
    communicate, so the program has no collectives. Under plain ``jit`` sharding propagation
    would keep the seed axis as a batch dimension of size 1 on every device: the slow batched
    dot that :func:`over_seeds` avoids (figures in docs/BENCHMARKS.md, "Seed axis").
    """
    init = over_seeds(trainer.init, (0, 0))
    chunk = over_seeds(trainer.chunk, (0, None))
    evaluate = over_seeds(trainer.evaluate, (0, 0))
    if sharding is None:
        return (jax.jit(init), jax.jit(chunk, donate_argnums=0), jax.jit(evaluate))
    from jax.sharding import PartitionSpec

    seed, rep = PartitionSpec("seed"), PartitionSpec()

    def per_device(f, in_specs, out_specs):
        # check_vma=False: the per-seed code's loops carry values the checker cannot type
        # (fresh constants next to per-device data); nothing here is reduced across devices.
        return jax.shard_map(
            f, mesh=sharding.mesh, in_specs=in_specs, out_specs=out_specs, check_vma=False
        )

    rep_sharding = replicated(sharding)
    return (
        jax.jit(
            per_device(init, (seed, seed), seed),
            in_shardings=(sharding, sharding),
            out_shardings=sharding,
        ),
        jax.jit(
            per_device(chunk, (seed, rep), (seed, seed)),
            in_shardings=(sharding, rep_sharding),
            out_shardings=(sharding, sharding),
            donate_argnums=0,
        ),
        jax.jit(
            per_device(evaluate, (seed, seed), seed),
            in_shardings=(sharding, sharding),
            out_shardings=sharding,
        ),
    )

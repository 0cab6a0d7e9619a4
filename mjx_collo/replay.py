"""On-device sequence replay for vmapped environments: ``init / add / sample / can_sample``.

Pure functions over :class:`ReplayState` (a flax struct dataclass), so the buffer lives inside the
compiled training chunk and can be vmapped over seeds and checkpointed with the train state.

Layout: one ring buffer per field, ``[S, N, *shape]`` (S rows per env, N envs), written one time
step for all N envs at a time with ``dynamic_update_slice`` (O(1) in capacity). All envs advance
together, so one write pointer ``pos`` and one fill count ``count`` serve all of them.

Row convention (LC/D1, shared with world_model.py): row t of an env holds

    obs_t, action_{t-1} (the action that led into obs_t; zeros at a reset),
    reward_t (received on arriving in obs_t; 0 at a reset), is_first_t.

Sequences are contiguous windows of one env's ring in time order. They may span episode
boundaries: ``is_first`` marks them and the RSSM resets its state inside the sequence. A window
never crosses the write pointer (the seam between the newest and the oldest row).

Capacity is given in env steps (``cfg.capacity``, per seed); with action repeat R the buffer holds
``capacity // R`` agent steps, split evenly across the N envs -- or, when the run is shorter, just
the rows the run writes (:func:`run_rows`): a 100k-step pixel run then holds 0.6 GiB per seed
instead of the 2.9 GiB a 500k capacity would reserve. A buffer sized for a shorter run grows when
the run is extended (:func:`resize`), bit for bit as if it had been allocated at the larger size.
"""

from __future__ import annotations

from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from mjx_collo.config import ReplayConfig


@struct.dataclass
class ReplayState:
    """data: field -> ``[S, N, *shape]``; pos: next row to write (int32 []); count: filled rows
    per env (int32 [], at most S)."""

    data: dict[str, jax.Array]
    pos: jax.Array
    count: jax.Array


def rows_per_env(
    cfg: ReplayConfig, num_envs: int, action_repeat: int, run: int | None = None
) -> int:
    """S = capacity (env steps) / action repeat / number of envs, or ``run`` (the rows a run
    writes per env, :func:`run_rows`) when that is fewer: nothing is ever overwritten then."""
    rows = cfg.capacity // action_repeat // num_envs
    if rows < cfg.length:
        raise ValueError(
            f"replay.capacity={cfg.capacity} env steps gives {rows} rows per env "
            f"(action_repeat={action_repeat}, num_envs={num_envs}), fewer than "
            f"replay.length={cfg.length}"
        )
    return rows if run is None else max(min(rows, run), cfg.length)


def run_rows(iterations: int, episode_len: int) -> int:
    """Rows one env writes in ``iterations`` agent steps with episodes of ``episode_len``: the
    first observation, one row per step and the first observation after each episode's end."""
    return 1 + iterations + iterations // episode_len


def resize(state: ReplayState, rows: int) -> ReplayState:
    """The buffer with ``rows`` rows per env holding the newest ``min(count, rows)`` rows in time
    order from row 0 (unbatched; vmap it over seeds). A buffer that never wrapped and fits keeps
    every row where it was, so growing or shrinking it changes no sample: :func:`sample` and
    :func:`add` only ever read rows below ``count``."""
    old = capacity_rows(state)
    keep = jnp.minimum(state.count, rows)
    i = jnp.arange(rows)
    src = (state.pos - keep + i) % old  # chronological: the oldest kept row first
    valid = i < keep

    def move(buf):
        out = buf[src]
        mask = valid.reshape((rows,) + (1,) * (buf.ndim - 1))
        return jnp.where(mask, out, jnp.zeros_like(out))

    return ReplayState(
        data={k: move(v) for k, v in state.data.items()},
        pos=(keep % rows).astype(jnp.int32),
        count=keep.astype(jnp.int32),
    )


def default_fields(
    obs_shape: tuple[int, ...], action_dim: int, obs_dtype: jnp.dtype = jnp.float32
) -> dict[str, jax.ShapeDtypeStruct]:
    """Per-row field specs: ``obs [*obs_shape]`` (uint8 for pixels), ``action [A]`` f32,
    ``reward []`` f32, ``is_first []`` bool."""
    return {
        "obs": jax.ShapeDtypeStruct(tuple(obs_shape), obs_dtype),
        "action": jax.ShapeDtypeStruct((action_dim,), jnp.float32),
        "reward": jax.ShapeDtypeStruct((), jnp.float32),
        "is_first": jax.ShapeDtypeStruct((), jnp.bool_),
    }


def init(
    cfg: ReplayConfig,
    num_envs: int,
    action_repeat: int,
    fields: Mapping[str, jax.ShapeDtypeStruct],
    run: int | None = None,
) -> ReplayState:
    """Empty buffer with ``rows_per_env`` rows per env for each field spec (one row, one env);
    ``run``: the rows the run writes per env (:func:`run_rows`), an upper bound on the size."""
    rows = rows_per_env(cfg, num_envs, action_repeat, run)
    data = {k: jnp.zeros((rows, num_envs) + tuple(f.shape), f.dtype) for k, f in fields.items()}
    return ReplayState(data=data, pos=jnp.zeros((), jnp.int32), count=jnp.zeros((), jnp.int32))


def capacity_rows(state: ReplayState) -> int:
    """S (static)."""
    return next(iter(state.data.values())).shape[0]


def add(state: ReplayState, row: Mapping[str, jax.Array]) -> ReplayState:
    """Write one time step for all envs: ``row[field]: [N, *shape]`` (every field; cast to the
    stored dtype). O(1) in capacity."""
    missing = set(state.data) ^ set(row)
    if missing:
        raise KeyError(f"replay.add: fields differ from the buffer's: {sorted(missing)}")
    rows = capacity_rows(state)
    data = {
        k: jax.lax.dynamic_update_index_in_dim(buf, row[k].astype(buf.dtype), state.pos, 0)
        for k, buf in state.data.items()
    }
    return ReplayState(
        data=data,
        pos=(state.pos + 1) % rows,
        count=jnp.minimum(state.count + 1, rows),
    )


def can_sample(state: ReplayState, length: int) -> jax.Array:
    """Whether each env holds at least one full window of ``length`` rows (bool [])."""
    return state.count >= length


def sample(state: ReplayState, key: jax.Array, batch: int, length: int) -> dict[str, jax.Array]:
    """``batch`` windows of ``length`` rows, uniform over envs and valid window starts.

    Returns field -> ``[batch, length, *shape]`` in the stored dtypes. Cost is a gather of
    ``batch * length`` rows, independent of capacity. Only meaningful when :func:`can_sample`.
    """
    rows = capacity_rows(state)
    num_envs = next(iter(state.data.values())).shape[1]
    k_env, k_start = jax.random.split(key)
    env = jax.random.randint(k_env, (batch, 1), 0, num_envs)
    oldest = (state.pos - state.count) % rows
    n_starts = jnp.maximum(state.count - length + 1, 1)
    offset = jax.random.randint(k_start, (batch, 1), 0, n_starts)
    idx = (oldest + offset + jnp.arange(length)[None, :]) % rows  # [B, L]
    return {k: buf[idx, env] for k, buf in state.data.items()}


def memory_bytes(state: ReplayState) -> int:
    """Bytes held by the buffer (works on concrete or ``jax.eval_shape`` states)."""
    return int(sum(np.prod(x.shape) * np.dtype(x.dtype).itemsize for x in state.data.values()))


def _human(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.1f} {unit}"
        n /= 1024
    raise AssertionError


def describe(state: ReplayState) -> str:
    """One line: rows x envs, per-field dtype/shape, total memory."""
    first = next(iter(state.data.values()))
    rows, envs = first.shape[:2]
    fields = ", ".join(
        f"{k} {np.dtype(x.dtype).name}{list(x.shape[2:])}" for k, x in state.data.items()
    )
    return f"replay: {rows} rows x {envs} envs ({fields}) = {_human(memory_bytes(state))}"

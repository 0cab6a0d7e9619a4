"""Orbax ``CheckpointManager`` wrapper for the seed-stacked train state.

A checkpoint directory ``<run>/checkpoints/<env_step>/`` holds three items:

* ``train``: the whole train state without the replay (params, optimizer states, RNG, counters);
* ``replay``: the replay buffer (optional: ``run.save_replay``); resuming without it starts from an
  empty buffer, evaluation never needs it;
* ``meta``: the resolved config, the format version and the schedule counters (JSON).

Orbax writes each step to a temporary directory and renames it when complete, so a crash mid-save
leaves the previous checkpoint intact; non-finite states are refused before anything is written.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

from mjx_collo import config as config_lib
from mjx_collo import replay as replay_lib
from mjx_collo.config import Config, ConfigError

FORMAT_VERSION = 1
# Config keys that may change between a run and its resume: how far to train, and where the
# evaluations run (not what they compute).
RESUMABLE = ("run.steps:", "run.eval_overlap:")


class CheckpointError(RuntimeError):
    """A checkpoint cannot be used (missing, wrong config, wrong format)."""


def all_finite(tree: Any) -> bool:
    """True if every floating-point leaf of ``tree`` is finite.

    Checked shard by shard on the host, not as a device reduction: over a seed-sharded array that
    reduction is a cross-device all-reduce, and with more CPU devices than cores (one device per
    seed, ``host_devices``) XLA aborts a collective whose participants do not all arrive within
    40 s. The processes of a multi-process run combine their answers, so all of them save or none.
    """
    ok = True
    for x in jax.tree.leaves(tree):
        shards = [s.data for s in x.addressable_shards] if isinstance(x, jax.Array) else [x]
        for shard in shards:
            a = np.asarray(shard)
            if np.issubdtype(a.dtype, np.floating) and not np.isfinite(a).all():
                ok = False
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        ok = bool(np.all(multihost_utils.process_allgather(np.asarray(ok))))
    return ok


def _strip_empty(tree: Any) -> Any:
    """Zero-size arrays (e.g. ``act`` of a model without actuator dynamics) -> None: Orbax cannot
    store them, and they carry no information."""
    return jax.tree.map(lambda x: None if int(np.prod(x.shape)) == 0 else x, tree)


def _fill_empty(abstract: Any, restored: Any) -> Any:
    """Put the zero-size arrays of ``abstract`` back into ``restored``."""

    def fill(a, r):
        if r is not None or a is None:
            return r
        sharding = getattr(a, "sharding", None)
        return jnp.zeros(a.shape, a.dtype, device=sharding)

    return jax.tree.map(fill, abstract, restored, is_leaf=lambda x: x is None)


def _on_this_host(abstract: Any) -> Any:
    """Give every leaf without a sharding this process's first device.

    Without one, Orbax restores each array onto the devices it was saved from, so a checkpoint
    written by a run whose seeds were sharded over 2 devices (``SEEDS=2`` on a 2-core CPU, or a GPU
    node) could not be evaluated or resumed where there is only one ("Topology mismatch")."""
    device = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])

    def place(x):
        if getattr(x, "sharding", None) is not None:
            return x
        return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=device)

    return None if abstract is None else jax.tree.map(place, abstract)


def replay_rows(replay: Any) -> int:
    """Rows per env of a seed-stacked replay (``[seeds, rows, envs, ...]`` leaves)."""
    return int(next(iter(replay.data.values())).shape[1])


def _with_rows(abstract: Any, rows: int) -> Any:
    """The seed-stacked abstract replay with ``rows`` rows per env."""

    def set_rows(x):
        shape = (x.shape[0], rows) + tuple(x.shape[2:])
        return jax.ShapeDtypeStruct(shape, x.dtype, sharding=getattr(x, "sharding", None))

    return abstract.replace(data={k: set_rows(v) for k, v in abstract.data.items()})


def _resized(replay: Any, abstract: Any) -> Any:
    """A restored seed-stacked replay moved to ``abstract``'s rows per env (replay.resize), on
    ``abstract``'s shardings."""
    rows = replay_rows(abstract)
    out = jax.jit(jax.vmap(lambda r: replay_lib.resize(r, rows)))(replay)
    return jax.tree.map(
        lambda x, a: jax.device_put(x, a.sharding) if getattr(a, "sharding", None) else x,
        out,
        abstract,
    )


def _step_dir(path: Path) -> tuple[Path, int | None]:
    """``<run>`` or ``<run>/checkpoints`` or ``<run>/checkpoints/<step>`` -> (manager dir, step)."""
    path = Path(path)
    if path.name.isdigit() and (path / "meta").exists():
        return path.parent, int(path.name)
    if (path / "checkpoints").is_dir():
        return path / "checkpoints", None
    return path, None


def _read_only_notice(record: logging.LogRecord) -> bool:
    return not str(record.msg).startswith("Given directory is read only")


class Checkpointer:
    def __init__(self, directory: str | Path, keep: int = 3, read_only: bool = False):
        self.directory, self.pinned_step = _step_dir(Path(directory).resolve())
        options = ocp.CheckpointManagerOptions(
            # read-only: the values orbax would otherwise force, each with a warning
            max_to_keep=None if read_only else keep,
            save_interval_steps=0 if read_only else 1,
            create=not read_only,
            read_only=read_only,
            enable_async_checkpointing=True,
        )
        # Read-only (make eval, possibly beside a training run still writing here) is what we asked
        # for; orbax announces it on every open as a warning.
        absl_log = logging.getLogger("absl")
        absl_log.addFilter(_read_only_notice)
        try:
            self.manager = ocp.CheckpointManager(self.directory, options=options)
        finally:
            absl_log.removeFilter(_read_only_notice)

    # ---- saving ------------------------------------------------------------------------------

    def save(self, step: int, train: Any, replay: Any | None, cfg: Config, meta: dict) -> bool:
        """Save (asynchronously) unless the state holds NaN/inf. Returns whether it saved."""
        if not all_finite(train):
            return False
        items = {
            "train": ocp.args.StandardSave(_strip_empty(train)),
            "meta": ocp.args.JsonSave(
                {
                    "format_version": FORMAT_VERSION,
                    "config": config_lib.to_dict(cfg),
                    "has_replay": replay is not None,
                    **meta,
                }
            ),
        }
        if replay is not None:
            items["replay"] = ocp.args.StandardSave(_strip_empty(replay))
        self.manager.save(step, args=ocp.args.Composite(**items), force=True)
        return True

    def wait(self) -> None:
        self.manager.wait_until_finished()

    def close(self) -> None:
        self.manager.wait_until_finished()
        self.manager.close()

    # ---- restoring ---------------------------------------------------------------------------

    def latest_step(self) -> int | None:
        if self.pinned_step is not None:
            return self.pinned_step
        return self.manager.latest_step()

    def steps(self) -> list[int]:
        """The checkpoint steps on disk, newest first (only the pinned one for a step directory)."""
        if self.pinned_step is not None:
            return [self.pinned_step]
        self.manager.reload()  # steps written or removed since this manager opened
        return sorted(self.manager.all_steps(), reverse=True)

    def meta(self, step: int | None = None) -> dict:
        step = self._resolve(step)
        out = self.manager.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))
        meta = dict(out["meta"])
        if meta.get("format_version") != FORMAT_VERSION:
            raise CheckpointError(
                f"checkpoint {self.directory / str(step)} has format version "
                f"{meta.get('format_version')}, this code reads {FORMAT_VERSION}"
            )
        return meta

    def newest_meta(self, on_skip: SkipFn | None = None) -> tuple[int, dict]:
        """The newest step whose metadata reads, and that metadata; steps whose metadata does not
        read (an empty or half-written step directory) are skipped and passed to ``on_skip``.

        Cheap (JSON only): what a resume checks its config against before compiling."""
        meta, step = self._first_usable(self.meta, on_skip)
        return step, meta

    def config(self, step: int | None = None) -> Config:
        return self.config_of(self.meta(step))

    def config_of(self, meta: dict) -> Config:
        try:
            return config_lib.build(config_lib.complete_saved(meta["config"]))
        except ConfigError as e:
            raise CheckpointError(f"checkpoint config no longer validates: {e}") from None

    def check_config(self, cfg: Config, meta: dict | None = None) -> None:
        """Raise :class:`CheckpointError` naming what differs if ``cfg`` is not the saved one
        (``meta``: a checkpoint's metadata, default the latest step's)."""
        saved = self.config_of(meta if meta is not None else self.meta())
        diffs = [d for d in config_lib.diff(saved, cfg) if not d.startswith(RESUMABLE)]
        if diffs:
            shown = "; ".join(diffs[:8]) + (" ..." if len(diffs) > 8 else "")
            raise CheckpointError(
                f"checkpoint in {self.directory} was written with a different config "
                f"(saved -> requested): {shown}. Use a new RUN directory, or the same settings."
            )

    def restore(
        self,
        abstract_train: Any,
        abstract_replay: Any | None = None,
        step: int | None = None,
        on_skip: SkipFn | None = None,
    ) -> tuple[Any, Any | None, dict, int]:
        """Restore into the given abstract (``jax.eval_shape``) trees; replay only if asked and
        saved. Returns (train, replay or None, meta, step). A replay saved with other rows per
        env than ``abstract_replay`` (a run extended past the steps its buffer was sized for, or
        one saved before replays were sized to the run) is moved to the abstract's rows
        (replay.resize: exact for a buffer that never wrapped).

        ``step=None`` takes the newest step that restores and holds only finite numbers: a
        damaged or partial newer step (a directory left empty, a file cut short, a metadata file
        missing) is skipped, named to ``on_skip(step, reason)``, and left where it is. A given
        ``step`` (or a step directory) is that step or an error."""
        abstract_train = _on_this_host(abstract_train)
        abstract_replay = _on_this_host(abstract_replay)

        def load(s: int) -> tuple[Any, Any | None, dict]:
            meta = self.meta(s)
            items = {"train": ocp.args.StandardRestore(_strip_empty(abstract_train))}
            saved_replay = None
            if abstract_replay is not None and meta.get("has_replay"):
                saved_replay = _with_rows(abstract_replay, self.saved_replay_rows(meta))
                items["replay"] = ocp.args.StandardRestore(_strip_empty(saved_replay))
            out = self.manager.restore(s, args=ocp.args.Composite(**items))
            train = _fill_empty(abstract_train, out["train"])
            replay = _fill_empty(saved_replay, out["replay"]) if "replay" in items else None
            if not all_finite(train):
                raise ValueError("the restored state holds NaN/inf")
            if replay is not None and replay_rows(replay) != replay_rows(abstract_replay):
                replay = _resized(replay, abstract_replay)
            return train, replay, meta

        (train, replay, meta), s = self._first_usable(load, on_skip, [step] if step else None)
        return train, replay, meta, s

    def saved_replay_rows(self, meta: dict) -> int:
        """Rows per env of a step's saved replay: recorded since replays are sized to the run;
        before that, always the capacity's (replay.rows_per_env without a run)."""
        if "replay_rows" in meta:
            return int(meta["replay_rows"])
        cfg = self.config_of(meta)
        return replay_lib.rows_per_env(cfg.replay, cfg.run.num_envs, cfg.env.action_repeat)

    def _first_usable(self, load, on_skip: SkipFn | None, steps: list[int] | None = None):
        """``(load(step), step)`` for the newest step that loads; the others before it are
        damaged: named to ``on_skip`` and, if none loads, in the error."""
        steps = steps if steps is not None else self.steps()
        if not steps:
            raise CheckpointError(f"no checkpoint found in {self.directory}")
        damaged = []
        for s in steps:
            try:
                with _quiet_unraisable():
                    return load(s), s
            except CheckpointError:
                raise
            except Exception as e:  # noqa: BLE001 - whatever a damaged directory makes orbax raise
                why = damage_reason(e)
                damaged.append(f"{s} ({why})")
                if on_skip is not None:
                    on_skip(s, why)
        raise CheckpointError(
            f"no usable checkpoint in {self.directory}: "
            + "; ".join(damaged)
            + ". Each step is a directory: move a damaged one aside to see what is left."
        )

    def _resolve(self, step: int | None) -> int:
        step = step if step is not None else self.latest_step()
        if step is None:
            raise CheckpointError(f"no checkpoint found in {self.directory}")
        return int(step)


SkipFn = Callable[[int, str], None]


@contextlib.contextmanager
def _quiet_unraisable():
    """While a step is read: a damaged array makes orbax's other read coroutines fail too, and
    Python prints each as an "Exception ignored in" traceback; the one-line reason is enough."""
    hook = sys.unraisablehook
    sys.unraisablehook = lambda _unraisable: None
    try:
        yield
    finally:
        gc.collect()  # the failed coroutines are finalized now, while the hook is quiet
        sys.unraisablehook = hook


def report_skips(log: Callable[[str], None]) -> SkipFn:
    """An ``on_skip`` that reports each damaged step once through ``log``."""
    seen: set[int] = set()

    def on_skip(step: int, why: str) -> None:
        if step not in seen:
            seen.add(step)
            log(f"checkpoint step {step} skipped, damaged or partial: {why}")

    return on_skip


def damage_reason(e: BaseException) -> str:
    """One short line for why a checkpoint step did not load."""
    text = " ".join(str(e).split())
    if isinstance(e, KeyError) and "Available items: []" in text:
        return "the step directory holds nothing (an interrupted or partial save)"
    if "error while reading array" in text:
        return "an array file does not read (cut short or corrupt)"
    text = text.split(" See full TensorStore details")[0]
    return f"{type(e).__name__}: {text[:160]}" if text else type(e).__name__


def host_tree(tree: Any) -> Any:
    """Device arrays -> numpy (for JSON/metrics)."""
    return jax.tree.map(np.asarray, jax.device_get(tree))

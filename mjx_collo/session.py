"""What the command-line scripts share: JAX setup, a run's default directory and size, and
loading a run's checkpoint for evaluation. ``train.py``, ``evaluate.py``, the benchmarks and the
tests import this module; they never import each other.

The env is not built here: scripts build it (``envs.from_config(cfg.env)``) and hand it over, so
the library does not depend on the task suite.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import socket
import time
from pathlib import Path
from typing import Any

from mjx_collo import config as config_lib
from mjx_collo.config import Config

# How a trained agent acts; every other key shapes what was trained, so `make eval` may override
# only these.
EVAL_SECTIONS = ("planner",)


def setup_jax() -> None:
    """Persistent compilation cache (``MJX_COLLO_CACHE``, default ``~/.cache/mjx_collo/xla``):
    re-running, resuming or evaluating the same config skips most of the XLA compile time."""
    import jax

    if jax.config.jax_compilation_cache_dir:  # already configured (e.g. by the test suite)
        return
    cache = Path(os.environ.get("MJX_COLLO_CACHE", Path.home() / ".cache" / "mjx_collo" / "xla"))
    cache.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(cache))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 2.0)


def default_run_dir(
    task: str,
    method: str,
    seeds: int,
    presets: list[str],
    sweep: str | None,
    overrides: list[str],
    first_seed: int = 0,
) -> Path:
    """``runs/<task>-<method>-s<seeds>[from<first seed>][-<presets>][-<hash of overrides and
    sweep>]``: deterministic per command, so re-running the same command resumes it."""
    seeds_part = f"s{seeds}" + (f"from{first_seed}" if first_seed else "")
    parts = [task, method, seeds_part] + presets
    extra = " ".join(sorted(overrides)) + (f" sweep={sweep}" if sweep else "")
    if extra:
        parts.append(hashlib.sha1(extra.encode()).hexdigest()[:8])
    return Path("runs") / "-".join(parts)


class RunLocked(RuntimeError):
    """Another live process holds the run directory."""


def lock_run_dir(run_dir: str | Path):
    """Hold ``<run_dir>/.lock`` (an OS file lock, ``flock``) for this process's lifetime: a second
    launch on the same directory fails at once, naming the holder, instead of interleaving its
    metrics and checkpoints with the first. The OS drops the lock when its holder dies, however
    it dies, so a lock left by a dead process is simply taken over. Returns the open lock file;
    keep a reference to it."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    f = open(run_dir / ".lock", "a+")  # noqa: SIM115 (held until the process exits)
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        f.seek(0)
        holder = f.read().strip() or "another process"
        f.close()
        raise RunLocked(
            f"{run_dir} is in use by {holder}: wait for that run to end (or stop it), or choose "
            "another run directory (RUN=...)"
        ) from None
    f.seek(0)
    f.truncate()
    f.write(
        f"pid {os.getpid()} on {socket.gethostname()} since {time.strftime('%Y-%m-%d %H:%M:%S')}"
    )
    f.flush()
    return f


def exit_on_signal(doing: str) -> None:
    """Until something installs its own handlers (the training loop does, to save first), SIGINT
    and SIGTERM end the process at once with one line and status 130 / 143.

    Installed first thing by the scripts, so Ctrl-C while importing, tracing or compiling stops
    within a second instead of being lost (JAX's compile threads would keep a normal exit
    waiting for minutes) or ending in a traceback. Nothing half-written is left: start-up writes
    only small files, each atomically, and no checkpoint."""
    import signal
    import sys

    def handler(signum, _frame):
        name = signal.Signals(signum).name
        print(f"{name} received while {doing}: stopped, nothing saved", file=sys.stderr, flush=True)
        os._exit(128 + signum)

    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, handler)


def exit_code(stopped: str) -> int:
    """The process exit status of a run that ``stopped`` as it did: 0 when it completed (or hit
    its chunk limit), 128 + the signal number after SIGINT / SIGTERM (130 / 143), so a scheduler
    can tell an interrupted run, to be requeued, from a finished one."""
    import signal

    if stopped in ("SIGINT", "SIGTERM"):
        return 128 + int(signal.Signals[stopped])
    return 0


def count_runs(seeds: int, sweep: str | None) -> int:
    """Seeds x swept values, counted from the raw sweep text (validated later, by
    ``config.parse_sweep``; this count only sizes the CPU devices before JAX starts)."""
    n = max(seeds, 1)
    for item in (sweep or "").replace(";", " ").split():
        values = [v for v in item.partition("=")[2].split(",") if v.strip()]
        n *= max(len(values), 1)
    return n


def eval_config(cfg: Config, overrides: list[str]) -> Config:
    """A checkpoint's config with evaluation-time ``planner.*`` overrides applied."""
    if not overrides:
        return cfg
    new = config_lib.build(
        config_lib.apply_overrides(config_lib.to_dict(cfg), overrides, EVAL_SECTIONS)
    )
    from mjx_collo.agent import uses_prior

    if uses_prior(new) and not uses_prior(cfg):
        raise config_lib.ConfigError(
            f"cannot evaluate with planner.init={new.planner.init}: this checkpoint was trained "
            f"with planner.init={cfg.planner.init} and holds no policy prior"
        )
    if (new.planner.kind == "dreamer") != (cfg.planner.kind == "dreamer"):
        raise config_lib.ConfigError(
            f"cannot evaluate a planner.kind={cfg.planner.kind} checkpoint with "
            f"planner.kind={new.planner.kind}: only dreamer checkpoints hold an actor, and the "
            "actor is their policy; switch between the planners (latco, collodreamer, cem, mppi, "
            "mppi_value) instead"
        )
    if uses_prior(cfg) and not uses_prior(new):
        # Acting without the prior its checkpoint holds (the planner alone: planner.init=cem, or
        # another planner.kind): actor.pg / bc / starts said how the prior trained, which an
        # evaluation does not do; the no-prior config takes their neutral values.
        actor = new.actor.model_copy(update={"pg": 1.0, "bc": 0.0, "starts": 0})
        new = new.model_copy(update={"actor": actor})
    return new


def restore_state(
    ckpt, cfg: Config, env: Any, meta: dict, replay: bool = False, step=None, on_skip=None
):
    """The seed-stacked train state of the newest checkpoint that restores (or of ``step``), the
    seed keys and the step restored; the replay only with ``replay=True`` (the checkpoint must
    hold one), else ``state.replay`` is None. Damaged newer steps are passed to ``on_skip``.

    cfg, meta: the checkpoint's own config and metadata (``ckpt.newest_meta``): the state's
    shapes follow them (the acting caches depend on planner.mpc_steps), whatever planner
    settings the evaluation then uses.
    """
    import jax
    import numpy as np

    from mjx_collo import parallel, trainer

    n = meta["num_runs"]
    keys = parallel.seed_keys(cfg, n, parallel.first_seed(meta["labels"]))
    # the swept values themselves are restored from the checkpoint (state.hyper); only shapes here
    hyper = {k: np.zeros(n, np.float32) for k in meta["labels"][0] if k != "seed"}
    init = trainer.make_train(cfg, env).init
    abstract = jax.eval_shape(jax.vmap(init), keys, hyper)
    state, rep, _, step = ckpt.restore(
        abstract.replace(replay=None), abstract.replay if replay else None, step, on_skip
    )
    return state.replace(replay=rep), keys, step

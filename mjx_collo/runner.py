"""Host side of a training run: build or resume, AOT-compile, loop over chunks, evaluate,
checkpoint, log. ``train.py`` is the CLI around :class:`Run`; it builds the env and hands it in.

Resuming: running again on a run directory that holds checkpoints restores the latest one (state,
replay, schedule) and continues exactly as if never interrupted; a different config is refused
with a message naming the differences.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from mjx_collo import checkpoint as ckpt_lib
from mjx_collo import config as config_lib
from mjx_collo import flops as flops_lib
from mjx_collo import host_devices, parallel
from mjx_collo import metrics as metrics_lib
from mjx_collo import replay as replay_lib
from mjx_collo import trainer as trainer_lib
from mjx_collo.config import Config


def is_main_process() -> bool:
    return jax.process_index() == 0


def host(tree: Any) -> Any:
    """Device values -> numpy on this host (all shards: gathered across processes if needed)."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        return jax.tree.map(
            lambda x: np.asarray(multihost_utils.process_allgather(x, tiled=True)), tree
        )
    return jax.device_get(tree)


class Evaluation(NamedTuple):
    """One evaluation of every run (:meth:`Run.start_evaluation`)."""

    returns: np.ndarray  # [runs, episodes]
    seconds: float
    prior: np.ndarray | None  # the policy prior acting alone on the same episodes, or None
    task: dict[
        str, np.ndarray
    ]  # the task's facts of the episodes, {name: [runs]} (Env.eval_metrics)


class TrainingDiverged(RuntimeError):
    """Persistent non-finite updates: the run stopped; the last good checkpoint is intact."""


def host_memory_bytes() -> int | None:
    """Memory this process may use: physical RAM, or the cgroup's limit where lower (containers,
    CI jobs); None where neither can be read."""
    try:
        limit = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):
        limit = None
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = Path(path).read_text().strip()
        except OSError:
            continue
        if text.isdigit():
            limit = int(text) if limit is None else min(limit, int(text))
    return limit


@dataclass
class RunResult:
    run_dir: Path
    env_steps: int
    eval_returns: list[tuple[int, np.ndarray]] = field(default_factory=list)
    compile_s: float = 0.0
    first_update_s: float | None = (
        None  # from run() start to the end of the first chunk that trained
    )
    init_s: float = 0.0  # building (or restoring) the state, its compile included
    chunk_s: list[float] = field(default_factory=list)  # wall time of each chunk call
    eval_s: list[float] = field(default_factory=list)  # wall time of each evaluation
    stopped: str = "completed"


def _labels_file(run_dir: Path, labels: list[dict]) -> None:
    tmp = run_dir / "seeds.json.tmp"
    tmp.write_text(json.dumps(labels, indent=1))
    tmp.replace(run_dir / "seeds.json")


def record_host(run_dir: Path, env_steps: int) -> None:
    """Append where this launch runs to ``host.json`` (one entry per launch: a resumed run may
    move between machines); study reports show it beside each cell's cost. Written atomically;
    an unreadable file is started afresh."""
    path = Path(run_dir) / "host.json"
    try:
        entries = json.loads(path.read_text()) if path.exists() else []
    except (OSError, json.JSONDecodeError):
        entries = []
    device = jax.devices()[0]
    entries.append(
        {
            "launched": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "from_env_step": int(env_steps),
            "host": socket.gethostname(),
            "platform": device.platform,
            "device_kind": device.device_kind,
            "cpu": host_devices.cpu_model(),
            "devices": jax.device_count(),
            "processes": jax.process_count(),
            "jax": jax.__version__,
        }
    )
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(entries, indent=1))
    tmp.replace(path)


class Run:
    """One (possibly resumed) run of ``cfg`` with ``num_seeds`` x sweep grid vmapped."""

    def __init__(
        self,
        cfg: Config,
        env: Any,
        run_dir: str | Path,
        num_seeds: int = 1,
        sweep: dict[str, list[float]] | None = None,
        progress: bool = True,
        log=print,
        first_seed: int = 0,
    ):
        self.cfg, self.env, self.log = cfg, env, log
        self.dir = Path(run_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.num_runs, self.hyper, self.labels = parallel.sweep_grid(
            sweep or {}, num_seeds, first_seed
        )
        self.trainer = trainer_lib.make_train(cfg, env)
        self.budget: dict[str, float] | None = None  # matmul work by schedule (compile())
        self.sharding = parallel.mesh_sharding(self.num_runs)
        self.init_fn, self.chunk_fn, self.eval_fn = parallel.batched(self.trainer, self.sharding)
        self.ckpt = ckpt_lib.Checkpointer(self.dir / "checkpoints", keep=cfg.run.keep_checkpoints)
        self.keys = self._put(parallel.seed_keys(cfg, self.num_runs, first_seed))
        self.hyper = self._put(self.hyper)
        self.main = is_main_process()
        self.progress = progress and self.main
        self._stop_signal: str | None = None
        self._damaged: set[int] = set()  # checkpoint steps that did not load
        self._eval_compiled = None
        self.eval_device = self._eval_device()
        self._eval_pool = (
            ThreadPoolExecutor(max_workers=1, thread_name_prefix="eval")
            if self.eval_device is not None
            else None
        )

    # ---- placement ---------------------------------------------------------------------------

    def _eval_device(self):
        """The device evaluations overlap the training on (``run.eval_overlap``), or None.

        One seed's planning matmuls keep ~1.3 of 2 CPU cores busy, so an evaluation on a second
        XLA device (``host_devices`` gives a single run two) runs on what the chunk leaves idle.
        Needs the run unsharded on the first device and a single process."""
        if not self.cfg.run.eval_overlap or self.sharding is not None or jax.process_count() > 1:
            return None
        devices = jax.local_devices()
        return devices[1] if len(devices) > 1 else None

    def _put(self, tree: Any) -> Any:
        """Host data with a leading seed axis -> (global) arrays sharded like the seed axis."""
        if self.sharding is None:
            return tree
        return jax.tree.map(
            lambda x: jax.make_array_from_callback(
                np.shape(x), self.sharding, lambda idx, x=np.asarray(x): x[idx]
            ),
            tree,
        )

    def _it(self, it: int) -> Any:
        if self.sharding is None:
            return jnp.int32(it)
        rep = parallel.replicated(self.sharding)
        return jax.make_array_from_callback((), rep, lambda idx: np.int32(it))

    # ---- state -----------------------------------------------------------------------------

    def _abstract(self):
        return jax.eval_shape(self.init_fn, self.keys, self.hyper)

    def resume_point(self) -> tuple[int, dict] | None:
        """The newest checkpoint whose metadata reads, checked against this command, or None
        for a fresh run. JSON only: a changed config or seed count is refused here, in a second,
        before anything compiles; damaged newer steps are named and skipped."""
        if not self.ckpt.steps():
            return None
        step, meta = self.ckpt.newest_meta(on_skip=self._skipped)
        self._check_meta(meta)
        return step, meta

    def _check_meta(self, meta: dict) -> None:
        self.ckpt.check_config(self.cfg, meta)
        if meta.get("num_runs") != self.num_runs or meta.get("labels") != self.labels:
            raise ckpt_lib.CheckpointError(
                f"checkpoint in {self.dir} holds {meta.get('num_runs')} seed/sweep runs "
                f"{meta.get('labels')}, this command asks for {self.num_runs} {self.labels}"
            )

    def _skipped(self, step: int, why: str) -> None:
        if step not in self._damaged:
            self._damaged.add(step)
            self.log(
                f"checkpoint {self.dir / 'checkpoints' / str(step)} skipped, damaged or partial: "
                f"{why}"
            )

    def _set_aside(self, restored: int) -> None:
        """Move damaged steps newer than the restored one to ``checkpoints.damaged/`` (kept for
        a look, never deleted): the resumed run saves those step numbers again."""
        newer = [s for s in self._damaged if s > restored]
        if not newer or not self.main:
            return
        aside = self.dir / "checkpoints.damaged"
        aside.mkdir(exist_ok=True)
        for s in sorted(newer):
            target = aside / str(s)
            n = 1
            while target.exists():
                target, n = aside / f"{s}.{n}", n + 1
            (self.dir / "checkpoints" / str(s)).rename(target)
            self.log(f"moved damaged checkpoint {s} to {target}")
        self.ckpt.manager.reload()

    def _start_ready(self, resume):
        state, iteration = self.start(resume)
        return jax.block_until_ready(state), iteration

    def check_memory(self, abstract=None, fraction: float = 0.8) -> None:
        """Refuse, before anything is allocated, replays that would not fit in this host's memory
        (CPU devices share it; pixel frames make this easy to hit): one line naming the fix.
        Assumes one process per host (a multi-process run holds its share of the runs)."""
        if jax.devices()[0].platform != "cpu":
            return
        host = host_memory_bytes()
        if host is None:
            return
        abstract = self._abstract() if abstract is None else abstract
        replay = replay_lib.memory_bytes(abstract.replay) / max(jax.process_count(), 1)
        # Measured: a run's resident memory peaks at about twice its replay (4 pixel seeds with
        # 2.9 GiB replays each were killed at 18.3 GB; with 0.6 GiB each they peaked at 11.2 GiB;
        # docs/BENCHMARKS.md "Pixels: memory"), so the replay is counted twice.
        need = 2 * replay
        if need > fraction * host:
            cap, steps = self.cfg.replay.capacity, self.cfg.run.steps
            gib = 1024**3
            raise config_lib.ConfigError(
                f"the replay needs {need / gib:.1f} GiB at its peak in this process (twice its "
                f"{replay / gib:.1f} GiB; {self.num_runs} run(s) in all), more than {fraction:.0%} of the "
                f"{host / gib:.1f} GiB it may use; lower replay.capacity (now {cap} env steps; "
                f"the replay holds the fewer of it and the run's {steps}) or train fewer seeds at once"
            )

    def start(self, resume: tuple[int, dict] | None = None) -> tuple[trainer_lib.TrainState, int]:
        """Fresh state, or the newest checkpoint's that restores (``resume``: from
        :meth:`resume_point`). Returns (state, iteration)."""
        if resume is None:
            if self.main:
                config_lib.dump_yaml(self.cfg, self.dir / "config.yaml")
                _labels_file(self.dir, self.labels)
            t = time.perf_counter()
            state = self.init_fn(self.keys, self.hyper)
            jax.block_until_ready(state)
            self.log(f"initialised {self.num_runs} run(s) in {time.perf_counter() - t:.1f}s")
            return state, 0
        abstract = self._abstract()
        if self.sharding is not None:
            abstract = jax.tree.map(
                lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=self.sharding), abstract
            )
        train_abs = abstract.replace(replay=None)
        train, replay, meta, step = self.ckpt.restore(
            train_abs, abstract.replay, on_skip=self._skipped
        )
        self._check_meta(meta)
        self._set_aside(step)
        if replay is None:
            self.log(
                "checkpoint has no replay (run.save_replay=false): resuming with an empty buffer"
            )
            replay = jax.jit(lambda s: s.replay)(self.init_fn(self.keys, self.hyper))
        state = train.replace(replay=replay)
        self.log(
            f"resumed from {self.dir / 'checkpoints' / str(step)} (env step {meta['env_steps']})"
        )
        if replay is not None and meta.get("has_replay"):
            saved, rows = self.ckpt.saved_replay_rows(meta), ckpt_lib.replay_rows(abstract.replay)
            if saved != rows:
                self.log(
                    f"replay moved from {saved} to {rows} rows per env: sized to this run's "
                    f"{self.cfg.run.steps} env steps (replay.resize)"
                )
        if self.main:  # the config in force now: a resume may change run.steps or eval_overlap
            config_lib.dump_yaml(self.cfg, self.dir / "config.yaml")
        return state, int(meta["iteration"])

    def save(self, state, iteration: int, env_steps: int, wait: bool = False) -> bool:
        replay = state.replay if self.cfg.run.save_replay else None
        ok = self.ckpt.save(
            env_steps,
            state.replace(replay=None),
            replay,
            self.cfg,
            {
                "iteration": iteration,
                "env_steps": env_steps,
                "num_runs": self.num_runs,
                "labels": self.labels,
                "replay_rows": ckpt_lib.replay_rows(state.replay),
            },
        )
        if wait:
            self.ckpt.wait()
        if not ok:
            self.log(f"checkpoint at env step {env_steps} NOT written: the state holds NaN/inf")
        return ok

    # ---- compile ---------------------------------------------------------------------------

    def lower(self, state, iteration: int):
        """Lower the chunk from shapes only: a fresh state and one restored by Orbax (whose arrays
        carry explicit shardings) then give the same program, so a resumed run hits the
        persistent compilation cache instead of compiling again."""

        def spec(x):
            return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=self.sharding)

        return self.chunk_fn.lower(jax.tree.map(spec, state), self._it(iteration))

    def compile(self, state, iteration: int):
        t = time.perf_counter()
        lowered = self.lower(state, iteration)
        one = jax.eval_shape(lambda r: jax.tree.map(lambda x: x[0], r), state)
        # The FLOP count traces one acting step and one update again (unbatched, ~5 s of Python):
        # it runs while XLA compiles the chunk with the GIL released.
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="flops") as pool:
            costs = pool.submit(self.trainer.costs, one)
            compiled = lowered.compile()
            secs = time.perf_counter() - t
            self.budget = flops_lib.matmul_budget(self.trainer, costs.result())
        cost = flops_lib.cost_summary(compiled)
        self.log(
            f"compiled chunk ({self.trainer.iterations_per_chunk} iterations x "
            f"{self.trainer.env_steps_per_iteration} env steps, {self.num_runs} run(s)) in "
            f"{secs:.1f}s, temp memory {cost.get('temp_mib', float('nan')):.0f} MiB; "
            f"{replay_lib.describe(one.replay)} per run"
        )
        b = self.budget
        self.log(
            f"matmul work per run (loops counted per iteration): planning call "
            f"{_flop(b['plan_call_gflop_per_env'])}/env, update {_flop(b['update_gflop'])}; "
            f"steady chunk {_flop(b['chunk_gflop'])}, evaluation {_flop(b['eval_gflop'])}; "
            f"whole run {_flop(b['run_gflop'])} ({100 * b['run_planning_share']:.0f}% planning)"
        )
        return compiled, secs

    def _start_and_compile(self):
        """Build (or restore) the state and compile the chunk at the same time.

        Everything a resume can refuse (config, seed count) is checked first, from the
        checkpoint's JSON. The chunk is lowered from the state's shapes alone (``jax.eval_shape``
        of init), so its compile needs nothing from the real state. Building the state
        jit-compiles and runs the env resets (cheetah's 200 settling steps) and the agent's
        initial carry: 35-40 s on 2 cores that used to run before the chunk's 50-100 s compile.
        XLA compiles with the GIL released, so the two overlap on a second core. Both run in
        worker threads: the main thread only waits, so a signal reaches its handler at once
        (``session.exit_on_signal``). Multi-process runs keep the serial order (every process must
        issue its collectives in the same order)."""
        t0 = time.perf_counter()
        resume = self.resume_point()
        abstract = self._abstract()
        self.check_memory(abstract)
        if jax.process_count() > 1:
            started = self.start(resume)
            init_s = time.perf_counter() - t0
            return started, init_s, self.compile(started[0], started[1])
        with ThreadPoolExecutor(max_workers=2, thread_name_prefix="start") as pool:
            pending = pool.submit(self.compile, abstract, 0)
            starting = pool.submit(self._start_ready, resume)
            started = starting.result()
            init_s = time.perf_counter() - t0
            compiled = pending.result()
        return started, init_s, compiled

    # ---- loop ------------------------------------------------------------------------------

    def _handle(self, signum, _frame):
        self._stop_signal = signal.Signals(signum).name
        self.log(f"{self._stop_signal} received: saving a checkpoint after this chunk")

    def evaluate(self, state, env_steps: int) -> np.ndarray:
        """``run.eval_episodes`` deterministic episodes per run: returns ``[runs, episodes]``."""
        return self.start_evaluation(state, env_steps).result().returns

    def start_evaluation(self, state, env_steps: int) -> Future:
        """Start the evaluation at ``env_steps``; the future gives an :class:`Evaluation`.

        With an evaluation device the state is copied there (the copy done before this returns,
        since the next chunk takes the state's buffers) and the episodes run in a thread while
        the caller goes on; otherwise they run here and the future is already done."""
        key = jax.vmap(lambda k: jax.random.fold_in(k, env_steps))(self.keys)
        # Episodes read the networks, not the replay: not copied (frames of a pixel run: GiBs).
        state = state.replace(replay=None)
        if self.eval_device is None:
            done: Future = Future()
            done.set_result(self._evaluate(state, key))
            return done
        moved = jax.block_until_ready(jax.device_put((state, key), self.eval_device))
        return self._eval_pool.submit(self._evaluate, *moved)

    def _evaluate(self, state, key) -> Evaluation:
        t = time.perf_counter()
        if self._eval_compiled is None:  # AOT from shapes, like the chunk (see lower())
            sharding = (
                self.sharding
                if self.eval_device is None
                else jax.sharding.SingleDeviceSharding(self.eval_device)
            )
            spec = lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding)  # noqa: E731
            self._eval_compiled = self.eval_fn.lower(
                jax.tree.map(spec, state), jax.tree.map(spec, key)
            ).compile()
        out = host(self._eval_compiled(state, key))
        prior = np.asarray(out["returns_prior"]) if "returns_prior" in out else None
        task = {k: np.asarray(v) for k, v in out["task"].items()}
        return Evaluation(np.asarray(out["returns"]), time.perf_counter() - t, prior, task)

    def run(self, total_env_steps: int | None = None, max_chunks: int | None = None) -> RunResult:
        cfg = self.cfg
        total = int(total_env_steps or cfg.run.steps)
        chunk_steps = cfg.run.chunk_env_steps
        total = -(-total // chunk_steps) * chunk_steps  # round up to whole chunks
        if total > -(-cfg.run.steps // chunk_steps) * chunk_steps:
            raise ValueError(
                f"run({total}) goes past run.steps={cfg.run.steps}, the steps the replay was "
                f"sized for; build the Runner with run.steps={total}"
            )
        launch = time.perf_counter()
        (state, it), init_s, (compiled, compile_s) = self._start_and_compile()
        per_iter = self.trainer.env_steps_per_iteration
        env_steps = it * per_iter
        if self.main:
            record_host(self.dir, env_steps)
        result = RunResult(self.dir, env_steps, init_s=init_s, compile_s=compile_s)
        log = metrics_lib.RunLog(
            self.dir,
            total,
            self.num_runs,
            start_step=env_steps,
            progress=self.progress,
            enabled=self.main,  # one writer in a multi-process run
        )
        if getattr(log, "torn", None):
            self.log(
                f"metrics.jsonl ended in a cut-off row (a crash mid-write), dropped: "
                f"{log.torn[:80]!r}"
            )
        # Wall time since the run's first launch: a resumed run continues from its last row's.
        wall0 = max((r.get("perf/wall_s", 0.0) for r in getattr(log, "rows", [])), default=0.0)
        wall = lambda: np.full(self.num_runs, wall0 + time.perf_counter() - launch)  # noqa: E731
        handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
        for s in handlers:
            try:
                signal.signal(s, self._handle)
            except ValueError:  # not the main thread
                pass
        pending: tuple[int, Future] | None = None  # the evaluation in flight: (env step, future)

        def collect(block: bool) -> None:
            """Log the evaluation in flight once it is done (``block``: wait for it)."""
            nonlocal pending
            if pending is None or not (block or pending[1].done()):
                return
            (step, future), pending = pending, None
            ev = future.result()
            result.eval_s.append(ev.seconds)
            result.eval_returns.append((step, ev.returns))
            row = {"eval/return": ev.returns.mean(1), "eval/return_std": ev.returns.std(1)}
            if ev.prior is not None:  # the policy prior acting alone, same episodes
                row.update(
                    {
                        "eval/return_prior": ev.prior.mean(1),
                        "eval/return_prior_std": ev.prior.std(1),
                    }
                )
            row.update({f"eval/{k}": v for k, v in ev.task.items()})
            row.update({"perf/eval_s": np.full(self.num_runs, ev.seconds), "perf/wall_s": wall()})
            log.write(step, "eval", row)
            log.progress(env_steps)

        chunks = 0
        last_saved = env_steps if self.ckpt.latest_step() == env_steps else None
        try:
            while env_steps < total and self._stop_signal is None:
                t = time.perf_counter()
                state, stacked = compiled(state, self._it(it))
                stacked = host(stacked)
                it += self.trainer.iterations_per_chunk
                env_steps = it * per_iter
                dt = time.perf_counter() - t
                result.chunk_s.append(dt)
                chunks += 1
                trained = np.isfinite(np.asarray(stacked.get("wm/loss/total", [np.nan]))).any()
                if result.first_update_s is None and trained:
                    result.first_update_s = time.perf_counter() - launch
                summary = metrics_lib.summarize_chunk(stacked)
                summary["perf/env_steps_per_s"] = np.full(self.num_runs, chunk_steps / dt)
                summary["perf/wall_s"] = wall()
                log.write(env_steps, "train", summary)
                log.progress(env_steps, {"sps": f"{chunk_steps / dt:.0f}"})
                streak = np.asarray(host(state.nonfinite_streak))
                if (streak > cfg.run.max_nonfinite).any():
                    bad = int(np.argmax(streak))
                    raise TrainingDiverged(
                        f"training diverged: run {bad} ({self.labels[bad]}) had {int(streak[bad])} "
                        f"consecutive non-finite world-model updates by env step {env_steps}; "
                        f"stopped without saving. Last good checkpoint: "
                        f"{self.ckpt.latest_step()} in {self.dir / 'checkpoints'}. Try a lower "
                        f"wm.optim.lr or wm.optim.clip."
                    )
                collect(block=False)
                if env_steps % cfg.run.eval_every == 0 or env_steps >= total:
                    collect(block=True)  # one evaluation in flight at most
                    pending = (env_steps, self.start_evaluation(state, env_steps))
                    collect(block=False)  # done already unless it overlaps the next chunk
                if env_steps % cfg.run.checkpoint_every == 0 or env_steps >= total:
                    if self.save(state, it, env_steps):
                        last_saved = env_steps
                log.plot()
                if max_chunks is not None and chunks >= max_chunks:
                    result.stopped = "max_chunks"
                    break
            collect(block=True)
            log.plot()  # the last evaluation (logged just now when it overlapped the last chunk)
            if self._stop_signal is not None:
                result.stopped = self._stop_signal
            if last_saved != env_steps:  # interrupted or stopped early: keep the work
                self.save(state, it, env_steps, wait=True)
        finally:
            self.ckpt.wait()  # before the caller's handlers return: a save is never cut short
            log.close()
            for s, h in handlers.items():
                try:
                    signal.signal(s, h)
                except ValueError:
                    pass
        result.env_steps = env_steps
        # where the run stopped, for callers that go on by hand (benchmarks/bench_train.py)
        self.state, self.iteration, self.chunk_program = state, it, compiled
        return result

    def close(self) -> None:
        if self._eval_pool is not None:
            self._eval_pool.shutdown(wait=True)
        self.ckpt.close()


def _flop(gflop: float) -> str:
    """'31.2 GFLOP', '4.10 TFLOP', '820 MFLOP'."""
    if gflop >= 1e3:
        return f"{gflop / 1e3:.2f} TFLOP"
    if gflop >= 1.0:
        return f"{gflop:.1f} GFLOP"
    return f"{gflop * 1e3:.0f} MFLOP"

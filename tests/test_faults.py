"""Faults long runs meet, done for real: bad sizes on the command line, a metrics log cut off by a
kill mid-write. Each test fails without its fix."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from mjx_collo import metrics

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.parametrize(
    "args, key",
    [
        (["--steps", "0"], "run.steps"),
        (["--steps", "-5"], "run.steps"),
        (["run.num_envs=0"], "run.num_envs"),
        (["run.chunk_env_steps=0"], "run.chunk_env_steps"),
    ],
)
def test_zero_or_negative_sizes_fail_with_one_line_before_compiling(tmp_path, args, key):
    """Before: STEPS=0 compiled, wrote a step-0 checkpoint and exited 0; a zero env count or
    chunk size ended in a ZeroDivisionError traceback."""
    proc = subprocess.run(
        [sys.executable, str(ROOT / "train.py"), "--env", "reacher", "--run", str(tmp_path / "r")]
        + args,
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={**os.environ, "MJX_COLLO_CACHE": str(tmp_path / "cache")},
        timeout=300,
    )
    err = proc.stderr.strip()
    assert proc.returncode == 2, (proc.stdout, err)
    assert len(err.splitlines()) == 1 and key in err and "greater than 0" in err, err
    assert "compiled" not in proc.stdout and not (tmp_path / "r" / "checkpoints").exists()


def _rows(steps):
    return [{"step": s, "seed": 0, "kind": "train", "train/return": float(s)} for s in steps]


def test_a_cut_off_last_metrics_row_is_dropped_and_reported_on_resume(tmp_path):
    """Before: a kill mid-write left half a JSON row, and resuming stopped with JSONDecodeError
    although the checkpoint was fine."""
    path = tmp_path / "metrics.jsonl"
    good = "".join(json.dumps(r) + "\n" for r in _rows([1000, 2000]))
    path.write_text(good + '{"step": 3000, "seed": 0, "ki')
    log = metrics.RunLog(tmp_path, 5000, 1, start_step=2000, progress=False)
    log.close()
    assert [r["step"] for r in log.rows] == [1000, 2000]
    assert log.torn == '{"step": 3000, "seed": 0, "ki'
    assert path.read_text() == good  # the history is kept, the torn row gone
    assert not (tmp_path / "metrics.jsonl.tmp").exists()


def test_a_bad_row_before_the_last_is_damage_and_named(tmp_path):
    path = tmp_path / "metrics.jsonl"
    lines = [json.dumps(r) for r in _rows([1000])] + ["garbage"] + [json.dumps(_rows([2000])[0])]
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"metrics.jsonl: line 2 is not a JSON row"):
        metrics.read_rows(path)


def _train(run_dir: Path, *args: str, **kw) -> subprocess.Popen:
    env = {
        **os.environ,
        # the trainer tests' programs: one device, the suite's compile flags (conftest.py)
        "XLA_FLAGS": f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=1",
    }
    cmd = [sys.executable, str(ROOT / "train.py"), "--env", "reacher_easy", "--run", str(run_dir)]
    return subprocess.Popen(
        cmd + list(args),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env=env,
        **kw,
    )


def test_a_second_launch_on_a_run_in_use_fails_naming_the_holder(tmp_path):
    """Before: two `make train` on the same RUN both ran to the end, interleaving their metrics
    (23 duplicated steps) and checkpoints, and both exited 0."""
    import socket

    from mjx_collo import session

    held = session.lock_run_dir(tmp_path / "r")  # the first run, alive
    proc = _train(tmp_path / "r", "--preset", "debug")
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 2, (out, err)
    err = err.strip()
    assert len(err.splitlines()) == 1, err
    assert f"pid {os.getpid()} on {socket.gethostname()}" in err and "in use" in err
    assert "compiled" not in out and not (tmp_path / "r" / "metrics.jsonl").exists()
    held.close()


def test_a_lock_left_by_a_killed_process_is_taken_over(tmp_path):
    """The lock is the OS's (flock), not a marker file: SIGKILL leaves the file but not the lock."""
    import signal

    from mjx_collo import session

    code = (
        "import sys, time; from mjx_collo import session; "
        f"f = session.lock_run_dir({str(tmp_path / 'r')!r}); print('locked', flush=True); "
        "time.sleep(60)"
    )
    child = subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, cwd=ROOT
    )
    assert child.stdout.readline().strip() == "locked"
    with pytest.raises(session.RunLocked, match=f"pid {child.pid} "):
        session.lock_run_dir(tmp_path / "r")
    child.send_signal(signal.SIGKILL)
    child.wait()
    assert (tmp_path / "r" / ".lock").exists()
    session.lock_run_dir(tmp_path / "r").close()  # taken over


@pytest.mark.parametrize(
    "sig, code",
    # one handler serves both; SIGINT (a compile and a chunk, ~40 s) runs in the slow suite to
    # keep `make test` under its 15 minutes
    [pytest.param("SIGINT", 130, marks=pytest.mark.slow), ("SIGTERM", 143)],
)
@pytest.mark.heavy
def test_an_interrupted_run_saves_and_exits_128_plus_the_signal(tmp_path, sig, code):
    """Before: a run stopped by SIGINT or SIGTERM saved its checkpoint and exited 0, like a run
    that finished, so a scheduler could not tell it to requeue the job."""
    import signal

    proc = _train(
        tmp_path / "r", "--preset", "debug", "--seeds", "2", "--steps", "40000", "--no-progress"
    )
    for line in proc.stdout:  # the first chunk's progress line: training is under way
        if line.startswith("step "):
            break
    proc.send_signal(getattr(signal, sig))
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == code, (out, err)
    assert f"{sig} at " in out
    ckpts = sorted(
        int(p.name) for p in (tmp_path / "r" / "checkpoints").iterdir() if p.name.isdigit()
    )
    assert ckpts and ckpts[-1] < 40000


# ---- damaged checkpoints -------------------------------------------------------------------


def _saved(directory: Path, steps=(10, 20, 30), cfg=None, num_runs=1):
    """A checkpoint directory holding ``steps``, each ``{"w": step}``, saved through the real
    Checkpointer (the train state is a small stand-in: restore does not depend on its shape)."""
    import jax.numpy as jnp

    from mjx_collo import checkpoint, config

    cfg = cfg or config.load(task="reacher_easy", presets=["debug"])
    ck = checkpoint.Checkpointer(directory, keep=10)
    for s in steps:
        meta = {"iteration": s, "env_steps": s, "num_runs": num_runs}
        meta["labels"] = [{"seed": i} for i in range(num_runs)]
        assert ck.save(s, {"w": jnp.full((256,), float(s))}, None, cfg, meta)
    ck.close()


def _biggest_file(d: Path) -> Path:
    return max((p for p in d.rglob("*") if p.is_file()), key=lambda p: p.stat().st_size)


DAMAGE = {
    "an empty newer step directory": (40, lambda d: (d / "40").mkdir()),
    "an array file cut short": (
        30,
        lambda d: os.truncate(_biggest_file(d / "30" / "train"), 10),
    ),
    "a missing metadata file": (30, lambda d: (d / "30" / "meta" / "metadata").unlink()),
    "a metadata file cut short": (
        30,
        lambda d: (d / "30" / "meta" / "metadata").write_text('{"format_version": 1, "con'),
    ),
}


@pytest.mark.parametrize("damage", list(DAMAGE))
@pytest.mark.parametrize("read_only", [False, True], ids=["resume", "eval"])
def test_restore_skips_a_damaged_step_names_it_and_keeps_it(tmp_path, damage, read_only):
    """Before: an empty newer step folder, a half-written file or a missing metadata file made
    resume and `make eval` fail with a 28-145-line traceback, and the intact older checkpoints
    were not used."""
    import jax

    from mjx_collo import checkpoint

    d = tmp_path / "checkpoints"
    _saved(d)
    bad, damage_fn = DAMAGE[damage]
    damage_fn(d)
    ck = checkpoint.Checkpointer(d, keep=10, read_only=read_only)
    skipped = []
    abstract = jax.eval_shape(lambda: {"w": jax.numpy.zeros((256,))})
    train, _, meta, step = ck.restore(abstract, on_skip=lambda s, why: skipped.append((s, why)))
    expected = 30 if bad == 40 else 20
    assert step == expected and meta["env_steps"] == expected
    assert float(train["w"][0]) == expected
    assert [s for s, _ in skipped] == [bad] and "\n" not in skipped[0][1]
    assert (d / str(bad)).exists()  # named, never deleted
    ck.close()


def test_when_no_step_restores_the_error_names_each_one(tmp_path):
    import jax

    from mjx_collo import checkpoint

    d = tmp_path / "checkpoints"
    _saved(d, steps=(10, 20))
    for s in (10, 20):
        (d / str(s) / "meta" / "metadata").unlink()
    ck = checkpoint.Checkpointer(d, read_only=True)
    with pytest.raises(checkpoint.CheckpointError) as e:
        ck.restore(jax.eval_shape(lambda: {"w": jax.numpy.zeros((256,))}))
    assert (
        "no usable checkpoint" in str(e.value) and "20 (" in str(e.value) and "10 (" in str(e.value)
    )


def _train_cli(run_dir: Path, *args: str, cache: Path | None = None) -> subprocess.Popen:
    # the suite's compile cache (conftest.py) unless the test gives its own
    env = {**os.environ, **({"MJX_COLLO_CACHE": str(cache)} if cache else {})}
    cmd = [sys.executable, str(ROOT / "train.py"), "--run", str(run_dir), "--no-progress"]
    return subprocess.Popen(
        cmd + list(args),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env=env,
    )


@pytest.mark.parametrize(
    "args, named",
    [
        (["wm.deter=48"], "wm.deter"),
        (["--seeds", "2"], "seed/sweep runs"),
    ],
)
def test_a_resume_that_differs_is_refused_before_compiling(tmp_path, args, named):
    """Before: a config mismatch on resume was reported only after a 77-99 s compile. The run's
    checkpoint here holds a stand-in state: the refusal reads only its metadata."""
    from mjx_collo import config

    cfg = config.load(task="reacher_easy", presets=["debug"])
    _saved(tmp_path / "r" / "checkpoints", steps=(400,), cfg=cfg)
    proc = _train_cli(tmp_path / "r", "--env", "reacher_easy", "--preset", "debug", *args)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 2, (out, err)
    err = err.strip()
    assert len(err.splitlines()) == 1 and named in err, err
    assert "compiled" not in out and "initialised" not in out


@pytest.mark.parametrize("sig, code", [("SIGINT", 130), ("SIGTERM", 143)])
def test_a_signal_during_start_up_stops_at_once_with_one_line(tmp_path, sig, code):
    """Before: Ctrl-C while the program traced or compiled was lost (the run trained to the end)
    or became a traceback 50 s later. With its own empty compile cache the compile takes tens of
    seconds, so the exit code and the missing "compiled" line show it stopped before that."""
    import signal
    import time

    proc = _train_cli(
        tmp_path / "r", "--env", "reacher_easy", "--preset", "debug", cache=tmp_path / "cache"
    )
    before = [proc.stdout.readline() for _ in range(1)]
    while not before[-1].startswith("mjx_collo: "):  # the run directory is taken
        assert before[-1] and len(before) < 20, before
        before.append(proc.stdout.readline())
    time.sleep(2.0)  # into tracing
    t = time.monotonic()
    proc.send_signal(getattr(signal, sig))
    out, err = proc.communicate(timeout=120)
    waited = time.monotonic() - t
    assert proc.returncode == code, (out, err)
    err = err.strip()
    assert len(err.splitlines()) == 1 and f"{sig} received while starting up" in err, err
    assert "compiled" not in out, out
    assert not (tmp_path / "r" / "checkpoints").exists() or not any(
        (tmp_path / "r" / "checkpoints").iterdir()
    )
    assert not list((tmp_path / "r").glob("*.tmp"))
    print(f"{sig} during start-up: exited {waited:.1f} s after the signal")


@pytest.mark.slow
def test_resume_and_eval_pass_over_a_damaged_newest_checkpoint(tmp_path):
    """End to end, files really cut: training resumes from the newest intact checkpoint, naming
    the damaged one and moving it aside (the run saves that step again); `make eval` evaluates
    the newest intact one and names the damaged one."""
    run = tmp_path / "r"
    base = ["--env", "reacher_easy", "--preset", "debug"]
    proc = _train_cli(run, *base, "--steps", "800")
    out, err = proc.communicate(timeout=900)
    assert proc.returncode == 0, (out, err)
    ckpts = run / "checkpoints"
    os.truncate(_biggest_file(ckpts / "800" / "train"), 10)

    proc = _train_cli(run, *base, "--steps", "1200")
    out, err = proc.communicate(timeout=900)
    assert proc.returncode == 0, (out, err)
    assert "checkpoint " in out and "800 skipped, damaged or partial" in out, out
    assert f"resumed from {ckpts / '400'}" in out, out
    assert (run / "checkpoints.damaged" / "800").is_dir()
    assert sorted(int(p.name) for p in ckpts.iterdir() if p.name.isdigit())[-2:] == [800, 1200]

    (ckpts / "1200" / "meta" / "metadata").unlink()
    ev = subprocess.run(
        [sys.executable, str(ROOT / "evaluate.py"), "--ckpt", str(run), "--episodes", "1"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=900,
    )
    assert ev.returncode == 0, (ev.stdout, ev.stderr)
    assert "checkpoint step 1200 skipped, damaged or partial" in ev.stderr
    assert "Traceback" not in ev.stderr
    assert (run / "eval_800.json").exists() and not (run / "eval_1200.json").exists()

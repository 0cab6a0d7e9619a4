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
        "MJX_COLLO_CACHE": str(ROOT / ".pytest_cache" / "xla"),
        "XLA_FLAGS": "--xla_force_host_platform_device_count=1",  # the trainer tests' programs
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


@pytest.mark.parametrize("sig, code", [("SIGINT", 130), ("SIGTERM", 143)])
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

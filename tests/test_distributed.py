"""Several devices and several processes: the seed axis sharded over 2 forced CPU devices gives
the same numbers as unsharded, and a 2-process ``jax.distributed`` run (loopback) trains the debug
preset through ``train.py``. Subprocesses, because the device count is fixed when JAX starts."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from mjx_collo import host_devices

ROOT = Path(__file__).resolve().parent.parent


def _env(devices: int | None = None) -> dict:
    """The suite's environment for a subprocess, with its compile flags but without a device
    count: ``devices`` forces one, else host_devices picks it."""
    env = dict(os.environ)
    flags = [f for f in env.get("XLA_FLAGS", "").split() if "device_count" not in f]
    if devices is not None:
        flags.append(f"--xla_force_host_platform_device_count={devices}")
    env["XLA_FLAGS"] = " ".join(flags)
    env["PYTHONPATH"] = f"{ROOT}{os.pathsep}{env.get('PYTHONPATH', '')}"
    return env


@pytest.mark.slow
def test_sharded_seed_axis_equals_unsharded():
    proc = subprocess.run(
        [sys.executable, str(ROOT / "tests" / "sharding_check.py")],
        env=_env(devices=2),
        capture_output=True,
        text=True,
        timeout=1500,
        cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["all_finite"]
    assert min(result["updates"]) > 0
    assert result["max_abs_diff"] <= 1e-5, result


def _train_debug(seeds: int, steps: int, run: Path) -> list[str]:
    """``train.py`` on reacher with the debug preset (the command line without extra flags)."""
    return [
        sys.executable,
        str(ROOT / "train.py"),
        *("--env", "reacher", "--preset", "debug", "--seeds", str(seeds), "--steps", str(steps)),
        *("--run", str(run), "--no-progress"),
    ]


def _train_ok(cmd: list[str], env: dict) -> subprocess.CompletedProcess:
    """Run a ``train.py`` command line in the repository; fail with its output tails unless it
    exits 0."""
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900, cwd=ROOT)
    assert proc.returncode == 0, f"stdout:\n{proc.stdout[-2000:]}\nstderr:\n{proc.stderr[-3000:]}"
    return proc


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_two_process_distributed_run_trains(tmp_path):
    port = _free_port()
    run = tmp_path / "dist"
    procs = [
        subprocess.Popen(
            [
                *_train_debug(seeds=2, steps=400, run=run),
                "--distributed",
                "--coordinator",
                f"127.0.0.1:{port}",
                "--num-processes",
                "2",
                "--process-id",
                str(i),
            ],
            env=_env(),
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i in range(2)
    ]
    outs = [p.communicate(timeout=1500) for p in procs]
    for p, (out, err) in zip(procs, outs, strict=True):
        assert p.returncode == 0, f"stdout:\n{out[-2000:]}\nstderr:\n{err[-3000:]}"
    assert "process 0/2" in outs[0][0] and "process 1/2" in outs[1][0]
    rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert {r["seed"] for r in rows} == {0, 1}
    assert any("wm/loss/total" in r for r in rows)
    assert (run / "checkpoints" / "400").is_dir()


# 3 seeds (more devices than cores) in make test-all only: make test stays under its 15 minutes
@pytest.mark.parametrize("seeds", [pytest.param(3, marks=pytest.mark.slow), 4])
@pytest.mark.heavy
def test_seeds_split_over_cpu_devices_and_save(tmp_path, seeds):
    """``train.py --seeds n`` splits the host into CPU devices (host_devices): on 2 cores 3 seeds
    get one device each, 4 seeds one device per core with 2 vmapped seeds each. Each run writes its
    checkpoint. More devices than cores (3 on 2): the pre-save NaN check once reduced over the
    sharded state on the devices, and XLA aborted that all-reduce when a participant did not
    arrive within 40 s; the check now runs on the host."""
    run = tmp_path / f"seeds{seeds}"
    env = _env()
    proc = _train_ok(_train_debug(seeds=seeds, steps=400, run=run), env)
    devices = host_devices.configure(seeds, {})
    split = f"{devices} cpu devices ({seeds // devices} run(s) each)"
    assert f"seed axis sharded over {split}" in proc.stdout
    rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert {r["seed"] for r in rows} == set(range(seeds))
    assert (run / "checkpoints" / "400").is_dir()


@pytest.mark.slow  # make test resumes a resized replay on one device (test_trainer.py)
def test_a_sharded_run_resumes_with_its_replay_grown(tmp_path):
    """4 seeds on 2 devices, trained further: the sharded replay, sized for 400 env steps, grows
    on resume (replay.resize)."""
    run = tmp_path / "seeds4"
    env = _env()
    _train_ok(_train_debug(seeds=4, steps=400, run=run), env)
    longer = _train_ok(_train_debug(seeds=4, steps=800, run=run), env)
    assert "resumed from" in longer.stdout and (run / "checkpoints" / "800").is_dir()
    assert "replay moved from 103 to 205 rows per env" in longer.stdout


@pytest.mark.heavy
def test_a_single_run_evaluates_on_a_second_device_with_the_same_returns(tmp_path):
    """One seed gets 2 CPU devices (host_devices): it trains on the first while its evaluations
    run on the second, overlapping the next chunk. The returns equal those of evaluating in line
    (run.eval_overlap=false), and every evaluation is logged and plotted, the last one included."""
    env = _env()
    returns = {}
    for name, extra in (("overlap", []), ("inline", ["run.eval_overlap=false"])):
        run = tmp_path / name
        proc = _train_ok(_train_debug(seeds=1, steps=800, run=run) + extra, env)
        overlapped = "evaluations run on cpu device 1 while the next chunk trains" in proc.stdout
        assert overlapped == (name == "overlap"), proc.stdout[-2000:]
        rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
        returns[name] = {r["step"]: r["eval/return"] for r in rows if r["kind"] == "eval"}
        # the curves were drawn after the last row (the final evaluation) was written: before,
        # an evaluation that overlapped the last chunk was logged after the last plot
        png = (run / "plots" / "returns.png").stat().st_mtime_ns
        assert png >= (run / "metrics.jsonl").stat().st_mtime_ns, name
    assert sorted(returns["overlap"]) == [400, 800]
    assert returns["overlap"] == returns["inline"]

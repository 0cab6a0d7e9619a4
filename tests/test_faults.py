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

"""The stderr filter of train.py / evaluate.py (mjx_collo.xla_log_filter), run in child processes:
it rebinds the process's fd 2, which a pytest worker must keep."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# The two lines jaxlib 0.9 logs for each executable loaded from the compile cache on a CPU whose
# LLVM model has the +prefer-no-gather/scatter tuning flags (abridged from this VM's AMD EPYC).
NOISE = (
    "E1204 03:48:04.452827    4118 cpu_aot_loader.cc:220] Loading XLA:CPU AOT result. Target"
    " machine feature +prefer-no-gather is not  supported on the host machine. Machine type used"
    " for XLA:CPU compilation doesn't match the machine type for execution. Compile machine"
    " features: [+64bit,+adx] vs host machine features: [64bit,adx]. This could lead to execution"
    " errors such as SIGILL.\n"
    "W1204 03:48:12.475758    4130 pjrt_executable.cc:642] Assume version compatibility. PjRt-IFRT"
    " does not track XLA executable versions.\n"
)
# A real feature mismatch (a cache from another machine) must stay visible.
REAL = (
    "E1204 03:48:04.452898    4118 cpu_aot_loader.cc:220] Loading XLA:CPU AOT result. Target"
    " machine feature +avx512f is not  supported on the host machine.\n"
)


def _child(body: str, **env: str) -> subprocess.CompletedProcess:
    code = (
        "import os, sys\n"
        "from mjx_collo import xla_log_filter\n"
        "xla_log_filter.install()\n"
        f"NOISE, REAL = {NOISE!r}, {REAL!r}\n" + body
    )
    return subprocess.run(
        [sys.executable, "-c", code],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT), **env},
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_drops_the_cache_false_alarm_and_keeps_everything_else():
    r = _child(
        "os.write(2, NOISE.encode()); os.write(2, REAL.encode()); os.write(2, b'xla kept\\n')\n"
        "print('python kept', file=sys.stderr)\n"
    )
    assert r.returncode == 0, r.stderr
    assert "prefer-no-gather" not in r.stderr and "Assume version compatibility" not in r.stderr
    assert "+avx512f is not" in r.stderr
    assert "xla kept" in r.stderr and "python kept" in r.stderr


def test_a_crash_keeps_the_last_lines():
    r = _child("os.write(2, b'F check failed: last words\\n')\nos.abort()\n")
    assert r.returncode != 0
    assert "last words" in r.stderr


def test_can_be_turned_off():
    r = _child("os.write(2, NOISE.encode())\n", MJX_COLLO_XLA_LOGS="all")
    assert r.returncode == 0
    assert "prefer-no-gather" in r.stderr

"""Keep two known false alarms of XLA's C++ runtime off the terminal of ``train.py`` and ``evaluate.py``.

On CPUs whose LLVM model carries the tuning flags ``+prefer-no-gather`` / ``+prefer-no-scatter``
(AMD Zen 4 EPYC, some Xeons), jaxlib 0.9 logs, for every executable it loads from the persistent
compile cache, two ERROR lines of ~2,500 characters each ("Target machine feature +prefer-no-gather
is not supported on the host machine ... could lead to execution errors such as SIGILL") and a
WARNING ("Assume version compatibility"). The executable was compiled on the same machine and
loads and runs correctly: the loader compares tuning preferences as if they were instruction sets
(openxla/xla#44565, jax-ml/jax#38445). A warm launch printed 6 such lines before its first chunk.

:func:`install` sends the process's file descriptor 2 (where XLA's C++ logging writes) through a
small filter process that drops exactly those lines and passes every other line through. Python's
own ``sys.stderr`` (progress bar, error messages, tracebacks) keeps writing to the terminal
directly, so nothing is delayed. The filter is a separate process, not a thread: if the trainer
dies (a segfault, a failed XLA check), whatever it wrote last is still in the pipe, and the
filter flushes it before it sees end-of-file and exits. It ignores SIGINT/SIGTERM, so a Ctrl-C
reaches only the trainer, which checkpoints and exits.

``MJX_COLLO_XLA_LOGS=all`` turns the filter off. Imports nothing from JAX.
"""

from __future__ import annotations

import atexit
import os
import re
import subprocess
import sys

NOISE = re.compile(
    rb"cpu_aot_loader\.cc:\d+\] Loading XLA:CPU AOT result\. "
    rb"Target machine feature \+prefer-no-(?:gather|scatter) is not"
    rb"|pjrt_executable\.cc:\d+\] Assume version compatibility\. PjRt-IFRT"
)

_FILTER = r"""
import re, signal, sys
signal.signal(signal.SIGINT, signal.SIG_IGN)
signal.signal(signal.SIGTERM, signal.SIG_IGN)
noise = re.compile(sys.argv[1].encode("latin-1"))
out = sys.stdout.buffer
for line in sys.stdin.buffer:
    if not noise.search(line):
        out.write(line)
        out.flush()
"""

_proc: subprocess.Popen | None = None


def install(environ: dict[str, str] | None = None) -> bool:
    """Route fd 2 through the filter; returns whether it did (once per process; not when
    ``MJX_COLLO_XLA_LOGS=all``). Call it from a script's ``__main__``, never inside a test
    process: it rebinds ``sys.stderr`` to the terminal's descriptor."""
    global _proc
    env = os.environ if environ is None else environ
    if _proc is not None or env.get("MJX_COLLO_XLA_LOGS") == "all":
        return False
    sys.stderr.flush()
    terminal = os.dup(2)
    _proc = subprocess.Popen(
        [sys.executable, "-c", _FILTER, NOISE.pattern.decode("latin-1")],
        stdin=subprocess.PIPE,
        stdout=terminal,
        stderr=terminal,
        start_new_session=True,  # terminal signals go to the trainer only
    )
    os.dup2(_proc.stdin.fileno(), 2)
    _proc.stdin.close()  # fd 2 is now the pipe's only write end here
    sys.stderr = open(  # noqa: SIM115 - lives as long as the process
        terminal, "w", buffering=1, encoding="utf-8", errors="backslashreplace", closefd=False
    )
    atexit.register(_close, terminal)
    return True


def _close(terminal: int) -> None:
    """At a normal exit: end the pipe, let the filter print what is left, then return, so that the
    last lines come before the shell's prompt."""
    sys.stderr.flush()
    os.dup2(terminal, 2)
    if _proc is not None:
        try:
            _proc.wait(timeout=5)
        except subprocess.TimeoutExpired:  # a child process of ours still holds the pipe
            pass

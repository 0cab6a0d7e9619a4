"""Shared test fixtures.

* A persistent XLA compilation cache for the session (``MJX_COLLO_TEST_CACHE``, default
  ``.pytest_cache/xla``): tests that build the same program (same config, same shapes) compile it
  once; a second ``make test`` on the same machine skips most compiles.
* Fast XLA compiles: the suite's programs are tiny and it is bound by compile time, so it compiles
  with LLVM's optimisations off (``--xla_backend_optimization_level=0``, set here in
  ``XLA_FLAGS`` and so inherited by the subprocesses the tests start). The programs are the same
  (XLA's HLO passes are unchanged; only the machine code is less optimised); cold, one chunk of
  the default trains and evaluates in 59 s instead of 83 s and the smoke study in 62 s instead
  of 157 s. ``make test-all`` compiles as users do (``MJX_COLLO_TEST_FULL_OPT=1``).
* ``dmc_pool``: the dm_control reference computations (the slow, pure-Python side of the env
  parity tests) run in one spawned background process, concurrently with MJX compiles here.
"""

from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

# `make test` runs pytest-xdist workers side by side: on a GPU, do not let each one grab 75% of
# its memory up front.
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
FAST_COMPILE = "--xla_backend_optimization_level=0"
if os.environ.get("MJX_COLLO_TEST_FULL_OPT") != "1" and FAST_COMPILE not in os.environ.get(
    "XLA_FLAGS", ""
):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {FAST_COMPILE}".strip()

import jax  # noqa: E402
import pytest  # noqa: E402

_CACHE = Path(
    os.environ.get("MJX_COLLO_TEST_CACHE", Path(__file__).parent.parent / ".pytest_cache" / "xla")
)
_CACHE.mkdir(parents=True, exist_ok=True)
jax.config.update("jax_compilation_cache_dir", str(_CACHE))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
# train.py / evaluate.py started by tests share the suite's cache (session.setup_jax reads it).
os.environ.setdefault("MJX_COLLO_CACHE", str(_CACHE))


@pytest.fixture(scope="session")
def dmc_pool():
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=1, mp_context=ctx) as pool:
        yield pool


def pytest_collection_modifyitems(config, items):
    """Start the long tests first. `make test` (`--dist loadgroup`) hands work units to its two
    xdist workers in collection order (xdist itself puts the units of most tests first, which is
    the trainer group), so a 100 s test collected last would run while the other worker idles.
    xdist groups (tests sharing one trained fixture, run by one worker: ~5 min cold) go first,
    then tests marked ``heavy`` (each ~30 s or more cold), each in collected order; the rest
    fill in behind them."""

    def rank(item):
        if item.get_closest_marker("xdist_group"):
            return 0
        return 1 if item.get_closest_marker("heavy") else 2

    items.sort(key=rank)

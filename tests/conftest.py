"""Shared test fixtures.

* A persistent XLA compilation cache for the session (``MJX_COLLO_TEST_CACHE``, default
  ``.pytest_cache/xla``): tests that build the same program (same config, same shapes) compile it
  once; a second ``make test`` on the same machine skips most compiles.
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

import jax  # noqa: E402
import pytest  # noqa: E402

_CACHE = Path(
    os.environ.get("MJX_COLLO_TEST_CACHE", Path(__file__).parent.parent / ".pytest_cache" / "xla")
)
_CACHE.mkdir(parents=True, exist_ok=True)
jax.config.update("jax_compilation_cache_dir", str(_CACHE))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


@pytest.fixture(scope="session")
def dmc_pool():
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=1, mp_context=ctx) as pool:
        yield pool

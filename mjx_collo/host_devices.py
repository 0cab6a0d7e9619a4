"""XLA CPU devices for the seeds of a run, so that they execute in parallel on a multi-core host.

XLA's CPU backend shows the whole host as a single device. Vmapped seeds then run as one stream of
batched matmuls (one weight set per seed), and one seed's small planning matmuls keep only about
1.3 of 2 cores busy (one default planning call: 233 ms on 2 cores, 303 ms pinned to one).
``--xla_force_host_platform_device_count=N`` splits the host into N devices. The trainer then
shards the seed axis over them (``trainer.batched``: ``shard_map``, each device its own block of
seeds, one seed unbatched), and the seeds' programs run side by side on the cores.

Must run before JAX initialises its backends. Only the CPU platform reads the flag: on a GPU or
TPU host the accelerators stay the devices. An ``XLA_FLAGS`` that already sets the count wins.
Imports nothing from JAX.

A single run gets two devices: it trains on the first, and its evaluations run on the second while
the next chunk trains (``run.eval_overlap``; ``runner.Run``), filling the cores one seed leaves idle.

When the runs outnumber the cores and split evenly over them, they get one device per core, each
vmapping ``runs / cores`` of them, instead of one device per run. On the 2-core VM, 4 seeds
measured back to back: 2 devices, steady chunk 82.0 s and 217 s per evaluation
(``bench_results/train_seeds4_2dev.json``); 4 devices, 82.3 s and 241 s
(``bench_results/train_seeds4_4dev_backtoback.json``, only its 4-seed row). The chunks tie; the
evaluations, 20 episodes of small planning matmuls, gain from 2 seeds sharing each matmul instead
of 4 single-threaded programs time-slicing 2 cores.

When the seeds' devices are a multiple of the host's cores, each device also runs its ops on one
thread (``--xla_cpu_multi_thread_eigen=false``): the devices are then the parallelism, and Eigen's
intra-op threads only contend for the same cores. On the 2-core VM, 4 seeds on 4 devices measured
back to back: steady chunk 99.7 s with the threads, 91.0 s without; evaluation 273 s and 269 s
(``bench_results/train_seeds4_eigen_on_worker.json``, ``bench_results/train_seeds_eigen.json``).
3 seeds on 2 cores keep the threads: a 3-seed reacher run without them took 68 min where the
same config with them had taken 58 min. A single run keeps them too: its training device needs
both cores while no evaluation runs.
"""

from __future__ import annotations

import os
import sys

FLAG = "xla_force_host_platform_device_count"
EIGEN_FLAG = "xla_cpu_multi_thread_eigen"
MAX_DEVICES = 16  # more CPU devices than this only add threads


def host_cores() -> int:
    """CPU cores this process may run on (its affinity mask, not the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def device_count_for(num_runs: int, max_devices: int = MAX_DEVICES) -> int:
    """Host devices for ``num_runs`` runs: one per run, or the largest divisor of ``num_runs``
    that is at most ``max_devices`` (the seed axis must split evenly over the devices)."""
    if num_runs < 1:
        raise ValueError(f"num_runs must be >= 1, got {num_runs}")
    return max(d for d in range(1, min(num_runs, max_devices) + 1) if num_runs % d == 0)


def configure(
    num_runs: int, environ: dict[str, str] | None = None, cores: int | None = None
) -> int | None:
    """Add the device-count flag for ``num_runs`` to ``XLA_FLAGS`` unless it is set already.

    One run gets 2 devices (training and its overlapped evaluations). More runs than ``cores``
    (default: :func:`host_cores`) that split evenly over them get one device per core; other counts
    get :func:`device_count_for`. Several runs on a multiple of ``cores`` devices also get
    single-threaded devices
    (``--xla_cpu_multi_thread_eigen=false``) unless ``XLA_FLAGS`` sets that. Returns the device count it
    set, or None when it left ``XLA_FLAGS`` alone (a count of 1, the user's own count, or JAX
    already imported in this process: the flag would have no effect here and would only leak
    into subprocesses, e.g. when tests call ``train.main``).
    """
    if environ is None and "jax" in sys.modules:
        return None
    env = os.environ if environ is None else environ
    flags = env.get("XLA_FLAGS", "")
    cores = host_cores() if cores is None else cores
    if num_runs == 1:
        n = 2
    elif cores > 1 and num_runs > cores and num_runs % cores == 0:
        n = cores  # one device per core, each vmapping num_runs / cores runs
    else:
        n = device_count_for(num_runs)
    if n == 1 or FLAG in flags:
        return None
    flags = f"{flags} --{FLAG}={n}".strip()
    if num_runs > 1 and n % cores == 0 and EIGEN_FLAG not in flags:
        flags += f" --{EIGEN_FLAG}=false"
    env["XLA_FLAGS"] = flags
    return n

"""XLA CPU devices for the seeds of a run, so that they execute in parallel on a multi-core host.

XLA's CPU backend shows the whole host as a single device. Vmapped seeds then run as one stream of
batched matmuls, and one seed's small planning matmuls keep only part of the cores busy.
``--xla_force_host_platform_device_count=N`` splits the host into N devices; the trainer shards
the seed axis over them (``parallel.batched``: ``shard_map``, each device its own block of seeds,
one seed unbatched), and the seeds' programs run side by side on the cores.

* One run gets two devices: it trains on the first, and its evaluations run on the second while
  the next chunk trains (``run.eval_overlap``).
* Runs that outnumber the cores and split evenly over them get one device per core, each vmapping
  ``runs / cores`` of them; other counts get one device per run (or the largest divisor <= 16).
* When several runs' devices are a multiple of the cores, each device runs single-threaded
  (``--xla_cpu_multi_thread_eigen=false``): the devices are the parallelism.

The measurements behind each rule are in docs/OPERATIONS.md. Must run before JAX initialises its
backends, so it imports nothing from JAX. An ``XLA_FLAGS`` that already sets the count wins, and
on a host where JAX will run on an accelerator (:func:`accelerator`) the flags are left alone:
there the GPU or TPU is the device, and several seeds share it vmapped.
"""

from __future__ import annotations

import glob
import importlib.util
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


# Instruction sets that change XLA's CPU matmul speed severalfold; the first the CPU has is named.
CPU_ISA = ("amx_tile", "avx512_bf16", "avx512f", "avx2")


def cpu_model() -> str:
    """The host CPU in words, e.g. ``AMD EPYC, avx512_bf16, 2 cores``: training speed differs
    ~2x between the VMs this project runs on, so every cost record names the CPU it was measured
    on (``host.json``, benchmark JSONs). Linux reads ``/proc/cpuinfo``; elsewhere ``platform``."""
    import platform

    name, flags = platform.processor() or platform.machine(), set()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key.strip() == "model name":
                    name = value.strip()
                elif key.strip() == "flags":
                    flags = set(value.split())
                    break
    except OSError:
        pass
    isa = next((i for i in CPU_ISA if i in flags), None)
    return ", ".join([name, *([isa] if isa else []), f"{host_cores()} cores"])


# JAX's accelerator plugins (``pip install 'jax[cuda12]'`` etc.) and what shows a device is present.
GPU_PLUGINS = ("jax_cuda12_plugin", "jax_cuda13_plugin", "jax_rocm60_plugin", "jax_rocm7_plugin")
GPU_DEVICE_FILES = ("/dev/nvidiactl", "/dev/kfd")


def accelerator(environ: dict[str, str] | None = None) -> str | None:
    """The accelerator JAX will run on, found without importing JAX: ``JAX_PLATFORMS`` when set
    (its first entry, None for ``cpu``), else ``"gpu"`` when a GPU plugin is installed and a GPU
    device file exists, ``"tpu"`` when libtpu is installed and a TPU device exists, else None."""
    env = os.environ if environ is None else environ
    platforms = env.get("JAX_PLATFORMS", "").strip().lower()
    if platforms:
        first = platforms.split(",")[0].strip()
        return None if first == "cpu" else first
    if any(importlib.util.find_spec(m) for m in GPU_PLUGINS) and any(
        os.path.exists(f) for f in GPU_DEVICE_FILES
    ):
        return "gpu"
    if importlib.util.find_spec("libtpu") and glob.glob("/dev/accel*"):
        return "tpu"
    return None


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
    set, or None when it left ``XLA_FLAGS`` alone: a count of 1, the user's own count, an
    accelerator host (:func:`accelerator`), or JAX already imported in this process (the flag
    would have no effect here and would only leak into subprocesses).
    """
    if environ is None and "jax" in sys.modules:
        return None
    env = os.environ if environ is None else environ
    if accelerator(env) is not None:
        return None
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

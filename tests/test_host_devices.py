"""CPU device split for multi-seed runs (mjx_collo/host_devices.py, session.count_runs)."""

from __future__ import annotations

import pytest

from mjx_collo import host_devices, session


@pytest.mark.parametrize(
    ("runs", "devices"), [(1, 1), (2, 2), (3, 3), (4, 4), (16, 16), (18, 9), (17, 1), (32, 16)]
)
def test_one_device_per_run_or_the_largest_divisor_that_fits(runs, devices):
    assert host_devices.device_count_for(runs) == devices


def test_configure_adds_the_flag_and_keeps_other_flags():
    env = {"XLA_FLAGS": "--xla_cpu_enable_fast_math=false"}
    assert host_devices.configure(3, env, cores=8) == 3
    assert env["XLA_FLAGS"] == (
        "--xla_cpu_enable_fast_math=false --xla_force_host_platform_device_count=3"
    )


def test_more_runs_than_cores_get_one_device_per_core_when_they_split_evenly():
    env: dict[str, str] = {}
    assert host_devices.configure(4, env, cores=2) == 2  # 2 vmapped runs per device
    assert env["XLA_FLAGS"] == (
        "--xla_force_host_platform_device_count=2 --xla_cpu_multi_thread_eigen=false"
    )
    assert host_devices.configure(16, {}, cores=8) == 8
    # runs that do not split evenly over the cores keep one device per run (or a divisor)
    assert host_devices.configure(6, env := {}, cores=4) == 6
    assert env["XLA_FLAGS"] == "--xla_force_host_platform_device_count=6"
    # no more runs than cores: one device each
    assert host_devices.configure(4, {}, cores=8) == 4


def test_seeds_filling_the_cores_run_single_threaded_devices():
    assert host_devices.configure(2, env := {}, cores=2) == 2
    assert env["XLA_FLAGS"].endswith("--xla_cpu_multi_thread_eigen=false")
    # 3 single-threaded devices on 2 cores leave one core shared by two: they keep the threads
    assert host_devices.configure(3, env := {}, cores=2) == 3
    assert env["XLA_FLAGS"] == "--xla_force_host_platform_device_count=3"
    # the user's own choice wins
    env = {"XLA_FLAGS": "--xla_cpu_multi_thread_eigen=true"}
    assert host_devices.configure(4, env, cores=2) == 2
    assert env["XLA_FLAGS"] == (
        "--xla_cpu_multi_thread_eigen=true --xla_force_host_platform_device_count=2"
    )


def test_one_run_gets_a_second_device_for_its_evaluations():
    # and keeps Eigen's threads: its training device needs both cores between evaluations
    env: dict[str, str] = {}
    assert host_devices.configure(1, env, cores=2) == 2
    assert env["XLA_FLAGS"] == "--xla_force_host_platform_device_count=2"


def test_configure_leaves_a_prime_run_count_and_the_users_own_count_alone():
    env: dict[str, str] = {}
    assert host_devices.configure(17, env) is None
    assert env == {}
    user = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    assert host_devices.configure(4, user) is None
    assert user["XLA_FLAGS"] == "--xla_force_host_platform_device_count=2"


def test_run_count_is_seeds_times_swept_values():
    assert session.count_runs(3, "value.gamma=0.9,0.99;wm.optim.lr=1e-4,3e-4,6e-4") == 18
    assert session.count_runs(2, None) == 2


def test_configure_does_nothing_once_jax_is_imported(monkeypatch):
    # pytest has imported JAX: the flag could not take effect and would leak into subprocesses
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    assert host_devices.configure(4) is None
    import os

    assert "XLA_FLAGS" not in os.environ


@pytest.mark.parametrize("platforms", ["cuda", "gpu", "tpu", "cuda,cpu"])
def test_an_accelerator_platform_leaves_the_cpu_flags_alone(platforms):
    """On a GPU or TPU host the accelerator is the device: no forced CPU device count, no
    single-threaded CPU devices, whatever the number of seeds."""
    for runs in (1, 4, 16):
        env = {"JAX_PLATFORMS": platforms, "XLA_FLAGS": "--xla_dump_to=/tmp/x"}
        assert host_devices.configure(runs, env, cores=2) is None
        assert env["XLA_FLAGS"] == "--xla_dump_to=/tmp/x"
    assert host_devices.configure(4, {"JAX_PLATFORMS": "cpu"}, cores=2) == 2


def test_an_installed_gpu_plugin_counts_only_with_a_gpu_present(monkeypatch):
    """A CUDA plugin installed on a machine without a GPU (JAX falls back to the CPU) keeps the
    CPU layout; with the NVIDIA device present the flags are left alone."""
    plugin = lambda name: object() if name == "jax_cuda12_plugin" else None  # noqa: E731
    monkeypatch.setattr(host_devices.importlib.util, "find_spec", plugin)
    monkeypatch.setattr(host_devices.os.path, "exists", lambda p: False)
    assert host_devices.accelerator({}) is None
    assert host_devices.configure(4, {}, cores=2) == 2
    monkeypatch.setattr(host_devices.os.path, "exists", lambda p: p == "/dev/nvidiactl")
    assert host_devices.accelerator({}) == "gpu"
    assert host_devices.configure(4, {}, cores=2) is None

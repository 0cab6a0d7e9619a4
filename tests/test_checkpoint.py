"""Checkpoints are never written with NaN/inf, and a refused save leaves the last good one."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjx_collo import checkpoint, config

ROOT = Path(__file__).resolve().parent.parent


def _state(w):
    return {"w": jnp.asarray(w, jnp.float32), "count": jnp.int32(3), "empty": jnp.zeros((0,))}


def test_all_finite_checks_every_floating_leaf():
    assert checkpoint.all_finite(_state([1.0, 2.0]))
    assert not checkpoint.all_finite(_state([1.0, np.nan]))
    assert not checkpoint.all_finite({"a": _state([1.0]), "b": np.array([np.inf])})
    assert checkpoint.all_finite({"ints": np.array([1, 2]), "none": None})


def test_a_state_with_nan_is_not_saved_and_the_last_good_one_stays(tmp_path):
    cfg = config.load(task="reacher_easy", presets=["debug"])
    ck = checkpoint.Checkpointer(tmp_path / "checkpoints", keep=3)
    assert ck.save(10, _state([1.0, 2.0]), None, cfg, {"env_steps": 10})
    ck.wait()
    assert not ck.save(20, _state([1.0, np.inf]), None, cfg, {"env_steps": 20})
    ck.wait()
    assert ck.latest_step() == 10
    abstract = jax.eval_shape(lambda: _state([0.0, 0.0]))
    train, _, meta, _ = ck.restore(abstract)
    np.testing.assert_array_equal(np.asarray(train["w"]), [1.0, 2.0])
    assert meta["env_steps"] == 10
    ck.close()


def test_opening_read_only_restores_without_warnings(tmp_path, caplog):
    """`make eval` opens the run's checkpoints read-only (a training run may still be writing
    there); orbax used to print three warnings about it on every open."""
    cfg = config.load(task="reacher_easy", presets=["debug"])
    ck = checkpoint.Checkpointer(tmp_path / "checkpoints", keep=3)
    assert ck.save(10, _state([1.0, 2.0]), None, cfg, {"env_steps": 10})
    ck.wait()
    ck.close()
    with caplog.at_level("WARNING"):
        ro = checkpoint.Checkpointer(tmp_path, read_only=True)
        train, _, meta, _ = ro.restore(jax.eval_shape(lambda: _state([0.0, 0.0])))
    assert meta["env_steps"] == 10 and ro.latest_step() == 10
    np.testing.assert_array_equal(np.asarray(train["w"]), [1.0, 2.0])
    assert [r.getMessage() for r in caplog.records if r.levelname == "WARNING"] == []
    ro.close()


def test_a_checkpoint_written_before_a_key_existed_still_loads(tmp_path):
    """Runs saved before ``planner.refine_iters`` / ``planner.value_lambda`` existed must evaluate
    and resume: their stored config gets the value that reproduces how they planned (no
    refinement, the value bootstrapped at the plan's end only), not today's default."""
    cfg = config.load(task="reacher_easy", presets=["debug"], overrides=["planner.refine_iters=7"])
    ck = checkpoint.Checkpointer(tmp_path / "checkpoints", keep=3)
    assert ck.save(10, _state([1.0]), None, cfg, {"env_steps": 10})
    ck.wait()
    old = config.to_dict(cfg)
    for key in config.ADDED_KEYS:  # nested keys (planner.init_cem.color) may be gone already
        *parents, name = key.split(".")
        node = old
        for p in parents:
            node = node.get(p, {})
        node.pop(name, None)
    with pytest.raises(config.ConfigError, match="refine_iters"):
        config.build(old)  # what an old stored config meets without the completion
    saved = config.complete_saved(old)
    assert config.build(saved).planner.refine_iters == 0
    assert config.build(saved).planner.value_lambda == 1.0
    # the CEM start of those runs (100 x 4) differs from today's default in whichever fields changed
    cem_then = config.ADDED_KEYS["planner.init_cem"]
    cem_now = {k: getattr(cfg.planner.init_cem, k) for k in cem_then}
    assert sorted(config.diff(config.build(saved), cfg)) == sorted(
        [
            "planner.refine_iters: 0 -> 7",
            f"planner.value_lambda: 1.0 -> {cfg.planner.value_lambda}",
            "run.eval_overlap: False -> True",  # where evaluations run: resumable (RESUMABLE)
            "wm.reward_head: 'mse' -> 'twohot'",  # the default ColloDreamer's since 2026-12-07
            f"actor.starts: 0 -> {cfg.actor.starts}",  # the default's prior, the same day
        ]
        + [
            f"planner.init_cem.{k}: {v} -> {cem_now[k]}"
            for k, v in cem_then.items()
            if v != cem_now[k]
        ]
    )
    assert ck.config(10).planner.refine_iters == 7  # a config that has the key keeps its value
    ck.close()


_SAVE_SHARDED = """
import sys, jax, jax.numpy as jnp, numpy as np
from mjx_collo import checkpoint, config
assert jax.device_count() == 2, jax.devices()
mesh = jax.sharding.Mesh(np.array(jax.devices()), ("seed",))
sharded = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("seed"))
state = {"w": jax.device_put(jnp.arange(8.0).reshape(2, 4), sharded), "count": jnp.int32(3)}
ck = checkpoint.Checkpointer(sys.argv[1], keep=3)
assert ck.save(10, state, None, config.load(task="reacher_easy", presets=["debug"]), {})
ck.close()
"""


def test_a_checkpoint_saved_sharded_over_two_devices_restores_on_one(tmp_path):
    """A run whose seeds were sharded over 2 devices (``SEEDS=2`` on 2 CPU cores, a GPU node) must
    evaluate and resume on a machine with one: Orbax would otherwise put the arrays back on the
    devices they were saved from and stop with "Topology mismatch"."""
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    env["PYTHONPATH"] = f"{ROOT}{os.pathsep}{env.get('PYTHONPATH', '')}"
    proc = subprocess.run(
        [sys.executable, "-c", _SAVE_SHARDED, str(tmp_path / "checkpoints")],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    ck = checkpoint.Checkpointer(tmp_path / "checkpoints", read_only=True)
    abstract = jax.eval_shape(lambda: {"w": jnp.zeros((2, 4)), "count": jnp.int32(0)})
    train, _, _, _ = ck.restore(abstract)
    np.testing.assert_array_equal(np.asarray(train["w"]), np.arange(8.0).reshape(2, 4))
    assert train["w"].sharding.device_set == {jax.local_devices()[0]}
    ck.close()


def test_where_evaluations_run_and_how_long_may_change_on_resume(tmp_path):
    """A run started with its evaluations beside training resumes with them in line, or longer;
    anything that changes what is computed is still refused with the key named."""
    cfg = config.load(task="reacher_easy", presets=["debug"])
    ck = checkpoint.Checkpointer(tmp_path / "checkpoints", keep=3)
    assert ck.save(10, _state([1.0]), None, cfg, {"env_steps": 10})
    ck.wait()
    ck.check_config(
        config.load(
            task="reacher_easy",
            presets=["debug"],
            overrides=["run.eval_overlap=false", "run.steps=9000"],
        )
    )
    other = config.load(task="reacher_easy", presets=["debug"], overrides=["run.eval_episodes=3"])
    with pytest.raises(checkpoint.CheckpointError, match="run.eval_episodes: 1 -> 3"):
        ck.check_config(other)


def test_conv_depth_differs_only_for_pixel_runs():
    """A resume compares configs with config.diff: a state run written before a change of the
    pixel encoder's default depth still resumes; a pixel run is refused, naming the key."""
    state_old = config.load(overrides=["wm.cnn_depth=32"])
    state_new = config.load(overrides=["wm.cnn_depth=16"])
    assert config.diff(state_old, state_new) == []
    px_old = config.load(overrides=["env.obs=pixels", "wm.cnn_depth=32"])
    px_new = config.load(overrides=["env.obs=pixels", "wm.cnn_depth=16"])
    assert config.diff(px_old, px_new) == ["wm.cnn_depth: 32 -> 16"]
    # the same for the pixel-only wm.decode_every
    assert config.diff(state_old, config.load(overrides=["wm.decode_every=4"])) == []
    px_every = config.load(overrides=["env.obs=pixels", "wm.cnn_depth=32", "wm.decode_every=4"])
    assert config.diff(px_old, px_every) == ["wm.decode_every: 1 -> 4"]
    assert "env.obs: 'state' -> 'pixels'" in config.diff(state_old, px_new)

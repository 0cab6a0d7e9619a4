"""Training from pixels (env.obs=pixels): the whole loop runs as one program with frames rendered in
the env step, stored uint8 in the replay and reconstructed by the world model's conv decoder.

One chunk on reacher (the cheapest to compile) runs in ``make test``; every other task in the
slow suite. Debug sizes (conv depth 4).
"""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest
import yaml

import envs
from mjx_collo import config, runner


def _one_chunk(task: str, tmp_path):
    cfg = config.load(task=task, presets=["debug"], overrides=["env.obs=pixels", "wm.cnn_depth=4"])
    env = envs.from_config(cfg.env)
    lines = []
    run = runner.Run(cfg, env, tmp_path / task, num_seeds=1, progress=False, log=lines.append)
    res = run.run(cfg.run.chunk_env_steps)
    obs = np.asarray(jax.device_get(run.state.replay.data["obs"]))
    run.close()
    return cfg, res, lines, obs


def _check(task, tmp_path):
    cfg, res, lines, obs = _one_chunk(task, tmp_path)
    assert any("obs uint8[64, 64, 3]" in line for line in lines), lines
    rows = [json.loads(x) for x in (res.run_dir / "metrics.jsonl").read_text().splitlines()]
    train = [r for r in rows if r["kind"] == "train"]
    evals = [r for r in rows if r["kind"] == "eval"]
    assert train and all(np.isfinite(r["wm/loss/obs"]) for r in train)
    assert evals and np.isfinite(evals[-1]["eval/return"])
    if task.startswith("quadruped"):  # the task's facts of each evaluation (Env.eval_metrics)
        n = cfg.run.eval_episodes
        assert 0 <= evals[-1]["eval/starts_on_feet"] <= n
        assert 0 <= evals[-1]["eval/got_up"] <= n - evals[-1]["eval/starts_on_feet"]
    else:
        assert "eval/starts_on_feet" not in evals[-1]
    saved = yaml.safe_load((res.run_dir / "config.yaml").read_text())
    assert saved["env"]["obs"] == "pixels"
    assert obs.dtype == np.uint8 and obs.shape[-3:] == (64, 64, 3)
    assert obs.max() > obs.min()  # frames were written, not zeros


@pytest.mark.heavy
def test_one_chunk_of_pixel_training_on_reacher(tmp_path):
    _check("reacher_easy", tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("task", ["cheetah_run", "quadruped_walk", "walker_walk"])
def test_one_chunk_of_pixel_training_on_every_task(task, tmp_path):
    _check(task, tmp_path)


def test_a_bad_obs_value_fails_with_one_line():
    with pytest.raises(config.ConfigError) as e:
        config.load(overrides=["env.obs=rgb"])
    msg = str(e.value)
    assert "env.obs" in msg and "pixels" in msg and "\n" not in msg.strip()


@pytest.mark.slow
def test_eval_video_of_a_pixel_run_also_shows_what_the_agent_saw(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    import imageio.v3 as iio

    cfg, res, _, _ = _one_chunk("cheetah_run", tmp_path)
    root = Path(__file__).resolve().parent.parent
    out = subprocess.run(
        [sys.executable, "evaluate.py", "--ckpt", str(res.run_dir), "--episodes", "1", "--video"],
        cwd=root,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    step = cfg.run.chunk_env_steps
    agent = iio.imread(res.run_dir / f"eval_{step}_run0_agent.gif")
    video = iio.imread(res.run_dir / f"eval_{step}_run0.gif")
    assert agent.shape[1:3] == (64, 64) and video.shape[1:3] == (128, 128)
    assert len(agent) == len(video) > 1


def test_a_replay_larger_than_the_machine_is_refused_before_compiling(tmp_path, monkeypatch):
    import time

    # debug preset: 2 envs, action repeat 2 -> 500k rows x 2 envs x 12 KiB of frames = 11.5 GiB (a
    # run as long as the capacity: a shorter one holds only its own rows),
    # held twice at the peak, against a machine said to have 8 GiB (the real one may have any amount)
    monkeypatch.setattr(runner, "host_memory_bytes", lambda: 8 * 1024**3)
    cfg = config.load(
        task="cheetah_run",
        presets=["debug"],
        overrides=[
            "env.obs=pixels",
            "wm.cnn_depth=4",
            "replay.capacity=2000000",
            "run.steps=2000000",
        ],
    )
    run = runner.Run(
        cfg, envs.from_config(cfg.env), tmp_path / "big", progress=False, log=lambda *_: None
    )
    t = time.perf_counter()
    with pytest.raises(
        config.ConfigError,
        match=r"needs 22\.9 GiB at its peak.*\(twice its 11\.5 GiB.* lower replay\.capacity",
    ):
        run.run()
    assert time.perf_counter() - t < 60  # no chunk compile (50-100 s) before the refusal
    run.close()

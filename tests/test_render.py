"""The in-XLA renderer (envs/render.py) and pixel observations (env.obs=pixels).

What a user of pixel training relies on: frames are deterministic uint8 images of the task's benchmark
camera; they change where something moves; the target and every body are in view; the same pose looks
like MuJoCo's own render of it (body silhouettes, checked against ``mujoco.Renderer`` through OSMesa,
which ``make test`` installs; where no OpenGL can run the check skips with the reason); and a pixel
env steps inside jit with one frame per agent step.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

import envs
from envs import render

ROOT = Path(__file__).resolve().parent.parent


_FRAMES = {}


def _pose(m, rng, scale=0.3):
    """The model's reference pose with every hinge turned by N(0, scale) radians."""
    q = m.qpos0.copy()
    for j in range(m.njnt):
        if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE:
            q[m.jnt_qposadr[j]] += scale * rng.standard_normal()
    return q


def _frame(env, qpos, target_xy=None, size=64):
    """(image, geom ids) of ``env`` posed at ``qpos`` (velocities zero); one jit per env."""
    key = (env.name, size)
    if key not in _FRAMES:
        _FRAMES[key] = render.pose_renderer(env, size)
    t = None if target_xy is None else jnp.asarray(target_xy, jnp.float32)
    image, ids = _FRAMES[key](jnp.asarray(qpos, jnp.float32), t)
    return np.asarray(image), np.asarray(ids)


@pytest.mark.parametrize("task", ["cheetah_run", "reacher_easy", "quadruped_walk", "walker_walk"])
def test_every_body_and_the_target_are_in_view_in_a_deterministic_uint8_frame(task):
    env = envs.make(task)
    m = env.mj_model
    drawn = {int(m.geom_bodyid[g]) for v in render.make_scene(m).geoms.values() for g in v}
    seen_bodies = set()
    rng = np.random.default_rng(0)
    for _ in range(3):  # a leg can hide another in one pose: every body is seen in some pose
        qpos = _pose(m, rng)
        target = [0.1, 0.1] if task.startswith("reacher") else None
        image, ids = _frame(env, qpos, target)
        again, _ = _frame(env, qpos, target)
        assert image.dtype == np.uint8 and image.shape == (64, 64, 3)
        np.testing.assert_array_equal(image, again)
        assert image.std() > 10, "a flat image"
        seen_bodies |= set(m.geom_bodyid[np.unique(ids[ids >= 0])].tolist())
        if task.startswith("reacher"):
            tid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "target")
            assert (ids == tid).sum() > 10, "the target is not in view"
    missing = sorted(
        mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b) or str(b) for b in drawn - seen_bodies
    )
    assert not missing, f"bodies never in view: {missing}"


def test_a_frame_changes_where_the_body_moves():
    env = envs.make("cheetah_run")
    m = env.mj_model
    qpos = np.zeros(m.nq)
    qpos[1] = 0.0  # rootz offset 0: standing height from the model
    image, ids = _frame(env, qpos)
    # The side camera tracks the centre of mass: moving the cheetah along x keeps it in place in the
    # frame and slides the floor under it.
    shifted = qpos.copy()
    shifted[0] += 0.25
    image2, ids2 = _frame(env, shifted)
    planes = m.geom_type == mujoco.mjtGeom.mjGEOM_PLANE
    body = (ids >= 0) & ~planes[np.maximum(ids, 0)]
    body2 = (ids2 >= 0) & ~planes[np.maximum(ids2, 0)]
    assert (body & body2).sum() / (body | body2).sum() > 0.95
    floor = (ids >= 0) & planes[np.maximum(ids, 0)] & ~body2
    assert np.abs(image.astype(int) - image2.astype(int))[floor].max() > 20, (
        "the floor did not move"
    )
    # A fixed camera (reacher's): turning the wrist changes the pixels of the hand, no others.
    env = envs.make("reacher_easy")
    m = env.mj_model
    qpos = np.zeros(m.nq)
    target = [0.0, -0.15]
    image, ids = _frame(env, qpos, target)
    qpos[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "wrist")] = 0.8
    image2, ids2 = _frame(env, qpos, target)
    changed = np.abs(image.astype(int) - image2.astype(int)).sum(-1) > 0
    hand = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, g) for g in ("hand", "finger")]
    moving = np.isin(ids, hand) | np.isin(ids2, hand)
    near = moving.copy()  # within one pixel of the hand in either pose
    for axis in (0, 1):
        for shift in (1, -1):
            near |= np.roll(moving, shift, axis)
    assert changed.sum() > 10
    assert not (changed & ~near).any(), (
        f"{(changed & ~near).sum()} pixels changed away from the hand"
    )


def test_reacher_target_is_drawn_where_the_task_put_it():
    env = envs.make("reacher_easy")
    m = env.mj_model
    tid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "target")
    centres = []
    for xy in ([0.15, 0.0], [-0.15, 0.0], [0.0, 0.15]):
        _, ids = _frame(env, np.zeros(m.nq), xy)
        rows, cols = np.nonzero(ids == tid)
        assert rows.size > 10
        centres.append((rows.mean(), cols.mean()))
    (r1, c1), (r2, c2), (r3, c3) = centres
    # the overhead camera: +x is right in the image, +y is up
    assert c1 - c2 > 20 and abs(r1 - r2) < 2
    assert r3 < r1 - 10


def test_a_pixel_env_steps_in_jit_with_one_frame_per_agent_step():
    env = envs.make(
        "cheetah_run", action_repeat=2, episode_length=1000, normalize_actions=True, obs="pixels"
    )
    assert env.observation_size == (64, 64, 3)
    s0 = jax.jit(env.reset)(jax.random.PRNGKey(0))
    step = jax.jit(env.step)
    s1 = step(s0, jnp.ones(env.action_size))
    for s in (s0, s1):
        assert s.obs.dtype == jnp.uint8 and s.obs.shape == (64, 64, 3)
        assert s.info["state_obs"].shape == (17,)
    assert int(s1.info["steps"]) == 2
    # one render in the traced step, outside the action repeat's scan (which PixelObs wraps; a
    # scan traces its body once, so the count alone would not tell)
    assert isinstance(env, envs.PixelObs) and isinstance(env.env, envs.EpisodeWrapper)
    calls = []
    draw = env._render_data
    env._render_data = lambda *a, **k: calls.append(1) or draw(*a, **k)
    try:
        jax.make_jaxpr(lambda s, a: env.step(s, a))(s0, jnp.ones(env.action_size))  # a fresh trace
    finally:
        env._render_data = draw
    assert len(calls) == 1
    # the frame is the render of the state after the repeat
    bare = env.unwrapped
    scene = render.make_scene(bare.mj_model, 64, 64, 0)
    d = s1.pipeline_state
    expect = render.render_data(scene, d, bare.render_geom_xpos(d, s1.info))
    np.testing.assert_array_equal(np.asarray(s1.obs), np.asarray(expect))
    assert np.any(np.asarray(s0.obs) != np.asarray(s1.obs))
    with pytest.raises(ValueError, match="unknown obs 'rgb'"):
        envs.make("cheetah_run", obs="rgb")


def _reference(tasks, states):
    """Runs the MuJoCo comparison in a subprocess (MUJOCO_GL is read when mujoco is imported)."""
    import ctypes.util

    gl = os.environ.get("MUJOCO_GL", "osmesa")
    if gl == "osmesa" and ctypes.util.find_library("OSMesa") is None:
        pytest.skip(
            "no libOSMesa for MuJoCo's renderer here (make gl installs Debian's libosmesa6)"
        )
    env = dict(os.environ, MUJOCO_GL=gl)
    cmd = [sys.executable, "-m", "envs.reference", *tasks, "--states", str(states)]
    return subprocess.run(
        cmd + ["--out", str(ROOT / ".pytest_cache" / "preview")],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )


def _check_iou(out):
    if out.returncode != 0 and "no OpenGL context" in out.stderr:
        pytest.skip(out.stderr.strip().splitlines()[-1])
    assert out.returncode == 0, out.stderr[-2000:]
    lines = [line for line in out.stdout.splitlines() if "IoU" in line]
    assert lines, out.stdout
    for line in lines:
        low = float(line.split(" min ")[1].split()[0])
        assert low >= 0.9, line


def test_body_silhouettes_match_mujocos_renderer_reacher():
    _check_iou(_reference(["reacher_easy"], 4))


@pytest.mark.slow
def test_body_silhouettes_match_mujocos_renderer_every_task():
    _check_iou(_reference(["all"], 6))

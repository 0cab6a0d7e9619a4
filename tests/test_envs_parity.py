"""MJX tasks against dm_control itself (the reference runs live; nothing is copied).

1. observation and reward on >= 100 physics states from dm_control rollouts equal dm_control's
   within 1e-4 (MJX in float64, so this checks the definitions; the float32 check below bounds
   round-off, which only matters for quadruped's contact-force sensors);
2. with dm_control's own solver options, one control step from the same state gives the same next
   observation within 1e-3 (float64);
3. with the tuned options, the mean return of a fixed uniform-random policy over 64 episodes lies
   within two standard errors of dm_control's (float32, the training configuration);
4. reset distributions match (reacher target radius and size; quadruped upright fraction and
   height).

Compiles are the expensive part (tens of seconds per task on 2 cores), so each task compiles one
float64 "parity" program and one float32 "rollout" program, shared by the tests below.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs

dmc = pytest.importorskip("dm_control")
import dmc_reference as ref  # noqa: E402

TASKS = envs.registered()
N_STATES = 102
EPISODE_BATCH = 8  # envs per rollout call (the smoke test's "8 envs vmapped for a full episode")
EPISODE_CALLS = 8  # 64 episodes in all


@functools.cache
def parity_data(task: str):
    """dm_control states + reference obs/reward before and after one control step, and the same
    from MJX in float64 (physics='dmc'). Cached per task: one compile serves tests 1 and 2."""
    dm, states = ref.rollout_states(task, N_STATES, seed=11)
    rng = np.random.default_rng(5)
    actions = ref.random_actions(rng, dm.action_spec(), len(states))
    ref_out = []
    for s, a in zip(states, actions, strict=True):
        ref.set_physics(dm, s)
        o0, r0 = ref.observe(dm)
        o1, r1 = ref.control_step(dm, a)
        ref_out.append((o0, r0, o1, r1))
    ref_o0, ref_r0, ref_o1, ref_r1 = (np.array(x) for x in zip(*ref_out, strict=True))

    stacked = {k: np.stack([s[k] for s in states]) for k in states[0]}
    with jax.enable_x64(True):
        env = envs.make(task, physics="dmc")

        def both(st, action):
            task_state = {k: v for k, v in st.items() if k == "target_xy"}
            s0 = env.state_from_physics(st["qpos"], st["qvel"], st["act"], **task_state)
            r0 = env._reward(s0.pipeline_state, s0.info)
            s1 = env.step(s0, action)
            return s0.obs, r0, s1.obs, s1.reward

        out = jax.jit(jax.vmap(both))(stacked, actions)
        mjx_o0, mjx_r0, mjx_o1, mjx_r1 = (np.asarray(x, np.float64) for x in out)
    return dict(
        ref=(ref_o0, ref_r0, ref_o1, ref_r1), mjx=(mjx_o0, mjx_r0, mjx_o1, mjx_r1), states=stacked
    )


@pytest.mark.parametrize("task", TASKS)
def test_observation_and_reward_match_dm_control(task):
    d = parity_data(task)
    ref_o0, ref_r0, _, _ = d["ref"]
    mjx_o0, mjx_r0, _, _ = d["mjx"]
    assert len(ref_o0) >= 100
    # float32 cast of the observation is the only loss: compare at float32 resolution + 1e-4.
    np.testing.assert_allclose(mjx_o0, ref_o0, atol=1e-4, rtol=1e-6)
    np.testing.assert_allclose(mjx_r0, ref_r0, atol=1e-4)
    assert np.any(ref_r0 > 0) or task == "reacher_hard", "states should exercise the reward"


@pytest.mark.parametrize("task", TASKS)
def test_one_control_step_matches_dm_control(task):
    d = parity_data(task)
    _, _, ref_o1, ref_r1 = d["ref"]
    _, _, mjx_o1, mjx_r1 = d["mjx"]
    np.testing.assert_allclose(mjx_o1, ref_o1, atol=1e-3, rtol=1e-5)
    np.testing.assert_allclose(mjx_r1, ref_r1, atol=1e-3)


@functools.cache
def float32_observations(task: str):
    d = parity_data(task)
    env = envs.make(task, physics="dmc")

    def obs(st):
        task_state = {k: v for k, v in st.items() if k == "target_xy"}
        return env.state_from_physics(st["qpos"], st["qvel"], st["act"], **task_state).obs

    return np.asarray(jax.jit(jax.vmap(obs))(d["states"])), d["ref"][0]


@pytest.mark.parametrize("task", ["cheetah_run", "quadruped_walk"])
def test_float32_observation_round_off_is_bounded(task):
    """float32 MJX (what training uses): kinematic observations within 1e-4; quadruped's
    acceleration-stage sensors (accelerometer, arcsinh toe force/torque, from the float32 contact
    solve) within 2e-3 relative."""
    obs32, ref_o0 = float32_observations(task)
    np.testing.assert_allclose(obs32, ref_o0, atol=1e-4, rtol=2e-3)
    if task == "quadruped_walk":
        np.testing.assert_allclose(obs32[:, :48], ref_o0[:, :48], atol=1e-4)


@functools.cache
def tuned_rollouts(task: str):
    """64 full episodes (8 calls x 8 vmapped envs) of a uniform-random policy, tuned physics."""
    env = envs.make(task)
    low, high = jnp.asarray(env.action_low), jnp.asarray(env.action_high)

    @jax.jit
    def episode(key):
        k_reset, k_act = jax.random.split(key)
        s0 = jax.vmap(env.reset)(jax.random.split(k_reset, EPISODE_BATCH))

        def body(s, k):
            a = jax.random.uniform(k, (EPISODE_BATCH, env.action_size), minval=low, maxval=high)
            s = jax.vmap(env.step)(s, a)
            finite = jnp.all(jnp.isfinite(s.obs)) & jnp.all(s.metrics["nan"] == 0)
            return s, (s.reward, finite)

        s, (rewards, finite) = jax.lax.scan(body, s0, jax.random.split(k_act, 1000))
        return dict(
            returns=rewards.sum(0),
            finite=finite.all(),
            obs0=s0.obs,
            qpos0=s0.pipeline_state.qpos,
            info0=s0.info,
            obs_last=s.obs,
            reward_shape=rewards.shape,
        )

    keys = jax.random.split(jax.random.PRNGKey(2026), EPISODE_CALLS)
    outs = [jax.device_get(episode(k)) for k in keys]
    return env, outs


@pytest.mark.parametrize("task", TASKS)
def test_smoke_full_episode_vmapped(task):
    env, outs = tuned_rollouts(task)
    out = outs[0]
    assert out["obs0"].shape == (EPISODE_BATCH, env.observation_size)
    assert out["obs0"].dtype == np.float32
    assert out["reward_shape"] == (1000, EPISODE_BATCH)
    assert out["finite"], "non-finite observation or NaN physics in a random-policy episode"
    assert np.all(np.isfinite(out["returns"]))
    # reset is random: different envs start differently
    assert np.unique(out["obs0"].round(5), axis=0).shape[0] == EPISODE_BATCH


def _within_two_se(a: np.ndarray, b: np.ndarray) -> tuple[bool, str]:
    se = np.sqrt(a.var(ddof=1) / len(a) + b.var(ddof=1) / len(b))
    diff = abs(a.mean() - b.mean())
    msg = f"MJX {a.mean():.2f} vs dm_control {b.mean():.2f} (diff {diff:.2f}, 2 SE {2 * se:.2f})"
    return diff <= 2 * se, msg


@pytest.mark.slow
@pytest.mark.parametrize("task", TASKS)
def test_random_policy_return_matches_dm_control(task):
    _, outs = tuned_rollouts(task)
    ours = np.concatenate([o["returns"] for o in outs]).astype(np.float64)
    theirs = ref.episode_returns(task, episodes=len(ours), seed=7)
    ok, msg = _within_two_se(ours, theirs)
    assert ok, msg


def test_reacher_reset_distribution():
    from dm_control import suite  # noqa: F401

    for task, size in (("reacher_easy", 0.05), ("reacher_hard", 0.015)):
        env, outs = tuned_rollouts(task)
        xy = np.concatenate([o["info0"]["target_xy"] for o in outs])
        radius = np.linalg.norm(xy, axis=1)
        assert radius.min() >= 0.05 - 1e-6 and radius.max() <= 0.20 + 1e-6
        dm = ref.load(task, seed=3)
        dm_radius = []
        for _ in range(200):
            dm.reset()
            dm_radius.append(np.linalg.norm(dm.physics.named.model.geom_pos["target", :2]))
            assert dm.physics.named.model.geom_size["target", 0] == pytest.approx(size)
        ok, msg = _within_two_se(radius, np.array(dm_radius))
        assert ok, f"{task} target radius: {msg}"
        assert env.target_size == pytest.approx(size)
        # the reward threshold is target + finger radius, read from dm_control's model
        finger = float(dm.physics.named.model.geom_size["finger", 0])
        assert env.target_size + envs.reacher.FINGER_SIZE == pytest.approx(size + finger)


def test_quadruped_reset_distribution():
    env, outs = tuned_rollouts("quadruped_walk")
    upright = np.concatenate([o["obs0"][:, 47] for o in outs])
    height = np.concatenate([o["qpos0"][:, 2] for o in outs])
    dm = ref.load("quadruped_walk", seed=4)
    dm_up, dm_h = [], []
    for _ in range(300):
        dm.reset()
        dm_up.append(float(dm.physics.torso_upright()))
        dm_h.append(float(dm.physics.named.data.qpos["root"][2]))
        assert dm.physics.data.ncon == 0
    for name, ours, theirs in (
        ("upright fraction", (upright > 0).astype(float), (np.array(dm_up) > 0).astype(float)),
        ("height", height, np.array(dm_h)),
    ):
        ok, msg = _within_two_se(ours, theirs)
        assert ok, f"quadruped reset {name}: {msg}"
    # heights lie on dm_control's 1 cm search grid
    np.testing.assert_allclose(height * 100, np.round(height * 100), atol=1e-3)

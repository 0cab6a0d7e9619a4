"""Helpers that run real dm_control (the reference) for the env parity tests."""

from __future__ import annotations

import numpy as np

DMC_NAMES = {
    "cheetah_run": ("cheetah", "run"),
    "reacher_easy": ("reacher", "easy"),
    "reacher_hard": ("reacher", "hard"),
    "quadruped_walk": ("quadruped", "walk"),
    "quadruped_run": ("quadruped", "run"),
    "walker_walk": ("walker", "walk"),
}


def load(task: str, seed: int):
    from dm_control import suite

    domain, name = DMC_NAMES[task]
    return suite.load(domain, name, task_kwargs={"random": seed})


def flat_obs(obs) -> np.ndarray:
    return np.concatenate([np.asarray(v, np.float64).reshape(-1) for v in obs.values()])


def task_state(task: str, physics) -> dict:
    if task.startswith("reacher"):
        return {"target_xy": np.array(physics.named.model.geom_pos["target", :2])}
    return {}


def random_actions(rng: np.random.Generator, spec, n: int) -> np.ndarray:
    return rng.uniform(spec.minimum, spec.maximum, size=(n,) + spec.shape)


def rollout_states(task: str, n_states: int, seed: int = 0, stride: int = 3):
    """Physics states visited by a uniform-random policy (several episodes if needed).

    Returns a list of dicts with qpos, qvel, act and task state, taken every ``stride`` steps.
    """
    env = load(task, seed)
    rng = np.random.default_rng(seed)
    spec = env.action_spec()
    states = []
    ts = env.reset()
    step = 0
    while len(states) < n_states:
        if ts.last():
            ts = env.reset()
        ts = env.step(random_actions(rng, spec, 1)[0])
        step += 1
        if step % stride == 0:
            p = env.physics
            states.append(
                dict(
                    qpos=p.data.qpos.copy(),
                    qvel=p.data.qvel.copy(),
                    act=p.data.act.copy(),
                    **task_state(task, p),
                )
            )
    return env, states


def set_physics(env, state) -> None:
    """Put ``state`` into the dm_control physics and run forward (positions, sensors, forces)."""
    p = env.physics
    p.data.qpos[:] = state["qpos"]
    p.data.qvel[:] = state["qvel"]
    if p.model.na:
        p.data.act[:] = state["act"]
    if "target_xy" in state:
        p.named.model.geom_pos["target", :2] = state["target_xy"]
    p.forward()


def observe(env) -> tuple[np.ndarray, float]:
    task, p = env.task, env.physics
    return flat_obs(task.get_observation(p)), float(task.get_reward(p))


def control_step(env, action) -> tuple[np.ndarray, float]:
    """One dm_control control step from the current physics state (legacy_step semantics)."""
    task, p = env.task, env.physics
    task.before_step(action, p)
    p.step(env._n_sub_steps)
    task.after_step(p)
    return observe(env)


def episode_returns(task: str, episodes: int, seed: int) -> np.ndarray:
    """Undiscounted returns of a uniform-random policy over full episodes."""
    env = load(task, seed)
    rng = np.random.default_rng(seed + 1)
    spec = env.action_spec()
    out = []
    for _ in range(episodes):
        ts = env.reset()
        total = 0.0
        while not ts.last():
            ts = env.step(random_actions(rng, spec, 1)[0])
            total += ts.reward
        out.append(total)
    return np.array(out)

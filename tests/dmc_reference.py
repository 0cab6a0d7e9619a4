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
            if task.startswith("reacher") and len(states) % 3 == 0:
                # The reward is sparse: put the target near the finger in a third of the states
                # (inside or just outside the threshold) so the reward is exercised both ways.
                finger = p.named.data.geom_xpos["finger", :2]
                offset = rng.uniform(-1, 1, 2) * 0.04
                p.named.model.geom_pos["target", :2] = finger + offset
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


def parity_reference(task: str, n_states: int, seed: int = 11, action_seed: int = 5) -> dict:
    """States from a random rollout, reference obs/reward at each state and after one control
    step with a random action (everything the parity tests need from dm_control)."""
    dm, states = rollout_states(task, n_states, seed=seed)
    rng = np.random.default_rng(action_seed)
    actions = random_actions(rng, dm.action_spec(), len(states))
    rows = []
    for s, a in zip(states, actions, strict=True):
        set_physics(dm, s)
        o0, r0 = observe(dm)
        o1, r1 = control_step(dm, a)
        rows.append((o0, r0, o1, r1))
    o0, r0, o1, r1 = (np.array(x) for x in zip(*rows, strict=True))
    stacked = {k: np.stack([s[k] for s in states]) for k in states[0]}
    return dict(states=stacked, actions=actions, obs0=o0, rew0=r0, obs1=o1, rew1=r1)


def reset_statistics(task: str, n: int, seed: int) -> dict:
    """Reset-distribution samples: reacher target radius/size, quadruped upright and height."""
    env = load(task, seed)
    out: dict[str, list] = {}
    for _ in range(n):
        env.reset()
        p = env.physics
        if task.startswith("reacher"):
            out.setdefault("radius", []).append(
                float(np.linalg.norm(p.named.model.geom_pos["target", :2]))
            )
            out.setdefault("size", []).append(float(p.named.model.geom_size["target", 0]))
            out.setdefault("finger", []).append(float(p.named.model.geom_size["finger", 0]))
        if task.startswith("quadruped"):
            out.setdefault("upright", []).append(float(p.named.data.xmat["torso", "zz"]))
            out.setdefault("height", []).append(float(p.named.data.qpos["root"][2]))
            out.setdefault("ncon", []).append(int(p.data.ncon))
    return {k: np.array(v) for k, v in out.items()}

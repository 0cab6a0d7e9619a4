"""MJX ports of the dm_control tasks used by ColloDreamer, registered by name.

>>> import envs
>>> env = envs.make("cheetah")                      # bare task: one dm_control control step
>>> train_env = envs.make("cheetah", action_repeat=2, episode_length=1000, num_envs=16)

Imports mujoco, mjx, jax and brax only; never mjx_collo.
"""

from __future__ import annotations

import contextlib
import io
from collections.abc import Callable

# mujoco-mjx 3.x prints "Failed to import warp / mujoco_warp" to stdout on import when the optional
# Warp backend (GPU only) is not installed. We never use it; keep the notice off every command's output
# and pass any other line through.
with contextlib.redirect_stdout(io.StringIO()) as _import_out:
    from mujoco import mjx  # noqa: F401
for _line in _import_out.getvalue().splitlines():
    if not _line.startswith(("Failed to import warp", "Failed to import mujoco_warp")):
        print(_line)

from brax.envs.base import Env  # noqa: E402

from envs import cheetah, quadruped, reacher, walker  # noqa: E402
from envs.base import PHYSICS, MjxTask  # noqa: E402
from envs.wrappers import (  # noqa: E402
    AutoResetWrapper,
    EpisodeWrapper,
    NormalizeActions,
    PixelObs,
    VmapWrapper,
)

_TASKS: dict[str, Callable[..., MjxTask]] = {
    "cheetah_run": cheetah.CheetahRun,
    "reacher_easy": reacher.reacher_easy,
    "reacher_hard": reacher.reacher_hard,
    "quadruped_walk": quadruped.quadruped_walk,
    "quadruped_run": quadruped.quadruped_run,
    "walker_walk": walker.WalkerWalk,
}

# Short names resolve to the paper's variants.
ALIASES = {
    "cheetah": "cheetah_run",
    "reacher": "reacher_easy",
    "quadruped": "quadruped_walk",
    "walker": "walker_walk",
}

_OVERRIDES = {
    "physics": "MJX options: 'tuned' (default) or 'dmc' (dm_control's own)",
    "action_repeat": "repeat each action N env steps, rewards summed (wraps EpisodeWrapper)",
    "episode_length": "episode limit in env steps (truncation); default 1000 when wrapping",
    "normalize_actions": "map actions in [-1, 1] to the actuator range",
    "obs": "'state' (default: the task's state vector) or 'pixels' (64x64 RGB uint8, PixelObs)",
    "num_envs": "batch of N envs (VmapWrapper)",
    "auto_reset": "fresh random reset when an episode ends (needs num_envs)",
}


OBS = ("state", "pixels")


class UnknownTaskError(ValueError):
    pass


def registered() -> list[str]:
    """Canonical task names (aliases: see ``ALIASES``)."""
    return sorted(_TASKS)


def canonical(name: str) -> str:
    """Resolve an alias (``cheetah``) to its task name (``cheetah_run``)."""
    key = name.strip().lower().replace("-", "_")
    key = ALIASES.get(key, key)
    if key not in _TASKS:
        valid = ", ".join(registered() + sorted(ALIASES))
        raise UnknownTaskError(f"unknown task {name!r}; valid tasks: {valid}")
    return key


def make(name: str, **overrides) -> Env:
    """Build a task by name. With no overrides: the bare task (one dm_control control step per
    ``step``, actions in actuator units, clamped to ``ctrlrange``). Overrides: see ``_OVERRIDES``.
    """
    unknown = sorted(set(overrides) - set(_OVERRIDES))
    if unknown:
        valid = "; ".join(f"{k}: {v}" for k, v in _OVERRIDES.items())
        raise TypeError(f"unknown override(s) {unknown} for envs.make; valid overrides — {valid}")
    physics = overrides.pop("physics", "tuned")
    if physics not in PHYSICS:
        raise ValueError(f"unknown physics {physics!r}; choose one of {PHYSICS}")
    env: Env = _TASKS[canonical(name)](physics=physics)
    if overrides.get("normalize_actions", False):
        env = NormalizeActions(env)
    repeat, limit = overrides.get("action_repeat"), overrides.get("episode_length")
    if repeat is not None or limit is not None:
        env = EpisodeWrapper(env, episode_length=limit or 1000, action_repeat=repeat or 1)
    obs = overrides.get("obs", "state")
    if obs not in OBS:
        raise ValueError(f"unknown obs {obs!r}; choose one of {OBS}")
    if obs == "pixels":
        env = PixelObs(env)
    num_envs = overrides.get("num_envs")
    if num_envs is not None:
        env = VmapWrapper(env, num_envs)
    if overrides.get("auto_reset", False):
        if num_envs is None:
            raise ValueError("auto_reset needs num_envs (it wraps a batch of envs)")
        env = AutoResetWrapper(env)
    return env


__all__ = [
    "ALIASES",
    "AutoResetWrapper",
    "EpisodeWrapper",
    "MjxTask",
    "NormalizeActions",
    "OBS",
    "PixelObs",
    "UnknownTaskError",
    "VmapWrapper",
    "canonical",
    "make",
    "registered",
]


def from_config(env_cfg) -> Env:
    """The task of a config's ``env`` section as the trainer drives it: action repeat, episode
    limit, actions in [-1, 1], the configured physics options. ``env_cfg`` is any object with
    ``task``, ``action_repeat``, ``episode_env_steps``, ``physics`` and ``obs``
    (``mjx_collo.config.EnvConfig``)."""
    return make(
        env_cfg.task,
        action_repeat=env_cfg.action_repeat,
        episode_length=env_cfg.episode_env_steps,
        normalize_actions=True,
        physics=env_cfg.physics,
        obs=getattr(env_cfg, "obs", "state"),
    )

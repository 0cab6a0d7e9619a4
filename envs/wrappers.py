"""Training wrappers over brax ``Env``: episode limit + action repeat, action normalisation,
camera images as observations, batched vmap, and auto-reset with a fresh random reset per episode.

brax's own ``AutoResetWrapper`` restarts every finished env from one cached first state (fine for
brax's agents, wrong for ours); here a finished env gets ``env.reset`` with a new key.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import Env, State, Wrapper


class EpisodeWrapper(Wrapper):
    """Repeat each action ``action_repeat`` times (rewards summed) and end the episode after
    ``episode_length`` env steps (a truncation: ``info["truncation"] = 1``, ``done = 1``).

    ``info["steps"]`` counts env (control) steps. A step whose physics went non-finite also ends
    the episode (``metrics["nan"] = 1``) and the remaining repeats are skipped.
    """

    def __init__(self, env: Env, episode_length: int = 1000, action_repeat: int = 2):
        super().__init__(env)
        if action_repeat < 1 or episode_length < 1:
            raise ValueError("action_repeat and episode_length must be >= 1")
        self.episode_length = int(episode_length)
        self.action_repeat = int(action_repeat)

    def reset(self, rng: jax.Array) -> State:
        state = self.env.reset(rng)
        info = dict(state.info)
        info["steps"] = jnp.zeros((), jnp.int32)
        info["truncation"] = jnp.zeros((), jnp.float32)
        return state.replace(info=info)

    def step(self, state: State, action: jax.Array) -> State:
        def one(carry, _):
            s, total = carry
            nxt = self.env.step(s, action)
            # After a non-finite step keep the (already flagged) state instead of stepping NaNs.
            nxt = jax.tree.map(lambda a, b: jnp.where(s.done > 0, a, b), s, nxt)
            return (nxt, total + jnp.where(s.done > 0, 0.0, nxt.reward)), None

        start = state.replace(done=jnp.zeros_like(state.done))
        (state, reward), _ = jax.lax.scan(
            one, (start, jnp.zeros((), jnp.float32)), None, length=self.action_repeat
        )
        steps = state.info["steps"] + self.action_repeat
        truncation = (steps >= self.episode_length).astype(jnp.float32)
        info = dict(state.info)
        info["steps"], info["truncation"] = steps, truncation
        done = jnp.maximum(state.metrics["nan"], truncation)
        return state.replace(reward=reward, done=done, info=info)


class NormalizeActions(Wrapper):
    """Actions in [-1, 1] mapped affinely to the actuator range (D1/LatCo ``NormalizeActions``).

    Identity for tasks whose range already is [-1, 1]; quadruped's lift [-1, 1.1] and extend
    [-0.8, 0.8] actuators are rescaled. Inputs outside [-1, 1] are clipped first.
    """

    def __init__(self, env: Env):
        super().__init__(env)
        base = env.unwrapped
        low, high = np.asarray(base.action_low), np.asarray(base.action_high)
        if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high))):
            raise ValueError("NormalizeActions needs finite actuator ctrlranges")
        # numpy, so they enter programs as literals (no device placement: multi-process safe)
        self._low, self._high = low.astype(np.float32), high.astype(np.float32)

    def step(self, state: State, action: jax.Array) -> State:
        a = jnp.clip(action, -1.0, 1.0)
        return self.env.step(state, self._low + (a + 1.0) * 0.5 * (self._high - self._low))


class PixelObs(Wrapper):
    """The observation becomes the task's benchmark camera image, ``uint8 [size, size, 3]``.

    Rendered by ``envs.render`` from the physics state once per agent step (after the action repeat:
    wrap ``EpisodeWrapper``, not the bare task) and at reset, inside whatever program steps the env.
    The state vector the task observes is kept in ``info["state_obs"]`` (the inner wrappers step on it;
    metrics and debugging read it). A step whose physics went non-finite shows a black frame.
    """

    def __init__(self, env: Env, size: int = 64):
        super().__init__(env)
        from envs import render

        self._bare = env.unwrapped
        self.size = int(size)
        self._scene = render.make_scene(
            self._bare.mj_model, self.size, self.size, render.camera_for(self._bare)
        )
        self._render_data = render.render_data

    @property
    def observation_size(self) -> tuple[int, int, int]:
        return (self.size, self.size, 3)

    def _observe(self, state: State) -> State:
        d = state.pipeline_state
        image = self._render_data(self._scene, d, self._bare.render_geom_xpos(d, state.info))
        image = jnp.where(state.metrics["nan"] > 0, jnp.zeros_like(image), image)
        info = dict(state.info)
        info["state_obs"] = state.obs
        return state.replace(obs=image, info=info)

    def reset(self, rng: jax.Array) -> State:
        return self._observe(self.env.reset(rng))

    def step(self, state: State, action: jax.Array) -> State:
        info = dict(state.info)
        inner = state.replace(obs=info.pop("state_obs"), info=info)
        return self._observe(self.env.step(inner, action))


class VmapWrapper(Wrapper):
    """``num_envs`` independent envs: ``reset(key)`` splits the key, ``step`` vmaps."""

    def __init__(self, env: Env, num_envs: int):
        super().__init__(env)
        self.num_envs = int(num_envs)

    def reset(self, rng: jax.Array) -> State:
        return jax.vmap(self.env.reset)(jax.random.split(rng, self.num_envs))

    def reset_each(self, keys: jax.Array) -> State:
        """Reset every env with its own key: ``keys [num_envs, 2]``."""
        return jax.vmap(self.env.reset)(keys)

    def step(self, state: State, action: jax.Array) -> State:
        return jax.vmap(self.env.step)(state, action)


class AutoResetWrapper(Wrapper):
    """After a step that ends an episode (``done``), the env restarts from a *fresh* random reset.

    Wraps a batched env (``VmapWrapper``). The returned state of a finished env is its new first
    state, with ``reward``/``done``/``info["truncation"]`` of the final step kept and the final
    observation stored in ``info["final_obs"]``. Resets are computed only on steps where some env finished (a
    ``lax.cond`` on the batch), so fixed-length episodes cost one reset per episode.
    """

    def __init__(self, env: VmapWrapper):
        super().__init__(env)
        self.num_envs = env.num_envs

    def reset(self, rng: jax.Array) -> State:
        k_reset, k_next = jax.random.split(rng)
        state = self.env.reset(k_reset)
        info = dict(state.info)
        info["reset_key"] = jax.random.split(k_next, self.num_envs)
        info["final_obs"] = state.obs
        return state.replace(info=info)

    def step(self, state: State, action: jax.Array) -> State:
        keys = state.info["reset_key"]
        state = self.env.step(state, action)
        done = state.done > 0
        final_obs = state.obs

        def fresh(s: State) -> State:
            split = jax.vmap(jax.random.split)(keys)
            new = self.env.reset_each(split[:, 0])
            pick = lambda a, b: jnp.where(done.reshape(done.shape + (1,) * (a.ndim - 1)), a, b)
            merged_ps = jax.tree.map(pick, new.pipeline_state, s.pipeline_state)
            obs = pick(new.obs, s.obs)
            # The new episode's info, except "truncation", which (like reward and done) describes
            # the step that just finished.
            info = {
                k: pick(new.info[k], v) if k in new.info and k != "truncation" else v
                for k, v in s.info.items()
            }
            info["reset_key"] = jnp.where(done[:, None], split[:, 1], keys)
            return s.replace(pipeline_state=merged_ps, obs=obs, info=info)

        state = jax.lax.cond(jnp.any(done), fresh, lambda s: s, state)
        info = dict(state.info)
        info["final_obs"] = final_obs
        return state.replace(info=info)

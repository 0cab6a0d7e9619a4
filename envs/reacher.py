"""reacher-easy / reacher-hard (dm_control ``suite/reacher.py``) on MJX.

dm_control moves the target by editing the *model* (``geom_pos['target']``) and sets its size on the
model. Contacts are disabled in this domain, so the target only enters the observation and the
reward: we keep ``target_xy`` in ``state.info`` and the size as a static task constant.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco

from envs import base
from envs.rewards import tolerance

BIG_TARGET = 0.05
SMALL_TARGET = 0.015
FINGER_SIZE = 0.01  # geom_size['finger', 0] in reacher.xml
CONTROL_DT = 0.02

# Tuned MJX options (evidence: envs/assets/README.md). Contacts are already disabled by the XML;
# the only constraint is the wrist limit, which Newton solves in one iteration. eulerdamp stays on
# (off blows up at dt = 0.02).
TUNED = dict(iterations=1, ls_iterations=4, eulerdamp=True)


def build_model(physics: str, target_size: float) -> mujoco.MjModel:
    spec = base.load_spec("reacher")
    m = spec.compile()
    m.geom_size[base.obj_id(m, "geom", "target"), 0] = target_size
    if physics == "tuned":
        base.tune_solver(m, TUNED["iterations"], TUNED["ls_iterations"], TUNED["eulerdamp"])
    return m


class Reacher(base.MjxTask):
    def __init__(self, target_size: float, name: str, physics: str = "tuned"):
        m = build_model(physics, target_size)
        super().__init__(m, CONTROL_DT, physics)
        self.name = name
        self.target_size = target_size
        self._finger = base.obj_id(m, "geom", "finger")
        self._target = base.obj_id(m, "geom", "target")

    def _task_info(self, target_xy=None):
        if target_xy is None:
            raise TypeError("reacher needs target_xy=(x, y), the target geom position")
        return {"target_xy": jnp.asarray(target_xy, jnp.float32).reshape(2)}

    def _initial(self, key):
        k_joint, k_angle, k_radius = jax.random.split(key, 3)
        m = self.mj_model
        qpos = base.uniform_limited_hinges(k_joint, m, jnp.zeros(m.nq))
        angle = jax.random.uniform(k_angle, (), minval=0.0, maxval=2 * jnp.pi)
        radius = jax.random.uniform(k_radius, (), minval=0.05, maxval=0.20)
        target = jnp.stack([radius * jnp.sin(angle), radius * jnp.cos(angle)])
        return self._data_at(qpos, jnp.zeros(m.nv)), {"target_xy": target}

    def _to_target(self, data, info):
        return info["target_xy"] - data.geom_xpos[self._finger, :2]

    def render_geom_xpos(self, data, info):
        return data.geom_xpos.at[self._target, :2].set(info["target_xy"])

    def _observe(self, data, info):
        return jnp.concatenate([data.qpos, self._to_target(data, info), data.qvel]).astype(
            jnp.float32
        )

    def _reward(self, data, info):
        dist = jnp.linalg.norm(self._to_target(data, info))
        return tolerance(dist, (0.0, self.target_size + FINGER_SIZE))


def reacher_easy(physics: str = "tuned") -> Reacher:
    return Reacher(BIG_TARGET, "reacher_easy", physics)


def reacher_hard(physics: str = "tuned") -> Reacher:
    return Reacher(SMALL_TARGET, "reacher_hard", physics)

"""walker-walk (dm_control ``suite/walker.py``) on MJX."""

from __future__ import annotations

import jax.numpy as jnp
import mujoco
import numpy as np

from envs import base
from envs.rewards import tolerance

STAND_HEIGHT = 1.2
WALK_SPEED = 1.0
CONTROL_DT = 0.025

# Tuned MJX options (evidence: envs/assets/README.md). Walker geoms already collide only with the
# floor (conaffinity 0); MJX keeps the deepest contacts per condim group.
TUNED = dict(iterations=2, ls_iterations=4, eulerdamp=False, max_contact_points=4)


def build_model(physics: str) -> mujoco.MjModel:
    spec = base.load_spec("walker")
    if physics == "tuned":
        base.add_numeric(spec, "max_contact_points", TUNED["max_contact_points"])
    m = spec.compile()
    if physics == "tuned":
        base.tune_solver(m, TUNED["iterations"], TUNED["ls_iterations"], TUNED["eulerdamp"])
    return m


class WalkerWalk(base.MjxTask):
    name = "walker_walk"

    def __init__(self, physics: str = "tuned", move_speed: float = WALK_SPEED):
        m = build_model(physics)
        super().__init__(m, CONTROL_DT, physics)
        self.move_speed = move_speed
        self._torso = base.obj_id(m, "body", "torso")
        self._speed = base.sensor(m, "torso_subtreelinvel")

    def _initial(self, key):
        m = self.mj_model
        qpos = base.uniform_limited_hinges(key, m, jnp.asarray(m.qpos0, jnp.float32))
        return self._data_at(qpos, jnp.zeros(m.nv)), {}

    def _observe(self, data, info):
        orientations = data.xmat[1:, 0][:, jnp.array([0, 2])]  # xmat[1:, ['xx', 'xz']]
        height = data.xpos[self._torso, 2:3]
        return jnp.concatenate([orientations.reshape(-1), height, data.qvel]).astype(jnp.float32)

    def _reward(self, data, info):
        height = data.xpos[self._torso, 2]
        standing = tolerance(height, (STAND_HEIGHT, np.inf), margin=STAND_HEIGHT / 2)
        upright = (1 + data.xmat[self._torso, 2, 2]) / 2
        stand = (3 * standing + upright) / 4
        speed = data.sensordata[self._speed][0]
        move = tolerance(
            speed,
            (self.move_speed, np.inf),
            margin=self.move_speed / 2,
            value_at_margin=0.5,
            sigmoid="linear",
        )
        return stand * (5 * move + 1) / 6

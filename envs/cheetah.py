"""cheetah-run (dm_control ``suite/cheetah.py``) on MJX."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from envs import base
from envs.rewards import tolerance

RUN_SPEED = 10.0
SETTLE_STEPS = 200  # dm_control: physics.step(nstep=200) with ctrl = 0 after randomising joints
CONTROL_DT = 0.01

# Tuned MJX options (evidence: envs/assets/README.md). Self-collisions never occur in cheetah, so
# floor-only contacts are exact; the solver settings were checked statistically against dm_control.
TUNED = dict(iterations=3, ls_iterations=6, eulerdamp=False, max_contact_points=6)


def build_model(physics: str) -> mujoco.MjModel:
    spec = base.load_spec("cheetah")
    if physics == "tuned":
        base.set_floor_only_contacts(spec, floor="ground")
        base.add_numeric(spec, "max_contact_points", TUNED["max_contact_points"])
    m = spec.compile()
    # <compiler settotalmass="14"/> (deprecated attribute), applied the supported way.
    mujoco.mj_setTotalmass(m, 14.0)
    mujoco.mj_setConst(m, mujoco.MjData(m))
    if physics == "tuned":
        base.tune_solver(m, TUNED["iterations"], TUNED["ls_iterations"], TUNED["eulerdamp"])
    return m


class CheetahRun(base.MjxTask):
    name = "cheetah_run"

    def __init__(self, physics: str = "tuned"):
        m = build_model(physics)
        super().__init__(m, CONTROL_DT, physics)
        self._speed = base.sensor(m, "torso_subtreelinvel")
        self._limited = m.jnt_limited.astype(bool)

    def _initial(self, key):
        m = self.mj_model
        lo, hi = m.jnt_range[:, 0], m.jnt_range[:, 1]
        u = jax.random.uniform(key, (m.nq,), minval=lo, maxval=hi)
        qpos = jnp.where(self._limited, u, jnp.asarray(m.qpos0, jnp.float32))
        data = self._data_at(qpos, jnp.zeros(m.nv))

        def settle(d, _):
            return self.substep(d), None

        # dm_control: physics.step(nstep=200) with ctrl = 0, then data.time = 0.
        data, _ = jax.lax.scan(settle, data, None, length=SETTLE_STEPS)
        return data.replace(time=jnp.zeros_like(data.time)), {}

    def _observe(self, data, info):
        return jnp.concatenate([data.qpos[1:], data.qvel]).astype(jnp.float32)

    def _reward(self, data, info):
        speed = data.sensordata[self._speed][0]
        return tolerance(
            speed, (RUN_SPEED, np.inf), margin=RUN_SPEED, value_at_margin=0.0, sigmoid="linear"
        )

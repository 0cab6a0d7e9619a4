"""quadruped-walk / quadruped-run (dm_control ``suite/quadruped.py``, ``Move`` task) on MJX."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from envs import base
from envs.rewards import tolerance

WALK_SPEED = 0.5
RUN_SPEED = 5.0
DEFAULT_TIME_LIMIT = 20.0
CONTROL_DT = 0.02
HEIGHT_STEP = 0.01  # dm_control raises the body in 1 cm steps until nothing touches
# Evaluation classes (eval_metrics; benchmarks/probe_quadruped.py uses the same): a start on its
# feet (torso z-axis within 60 degrees of vertical at reset), an episode that ended up.
START_ON_FEET = 0.5
ENDED_UP = 0.8
ENDED_UP_STEPS = 100  # agent steps at the episode's end

# Tuned MJX options (evidence: envs/assets/README.md): floor-vs-body contacts only (dm_control
# also lets legs touch each other and the torso; the random-policy return is unchanged), the
# deepest max_contact_points contacts, 4 Newton / 8 line-search iterations with eulerdamp on (as
# dm_control). Not 2 / 4 with eulerdamp off (the choice until 2026-12-06): under temporally
# correlated actions that model went non-finite and flipped itself off its back by energy
# injection (29 of 60 down starts under pink noise; dm_control's options: 0), which is the skill
# quadruped_walk's return depends on.
TUNED = dict(iterations=4, ls_iterations=8, eulerdamp=True, max_contact_points=8)

_GEOM = mujoco.mjtGeom


def build_model(physics: str, floor_size: float) -> mujoco.MjModel:
    spec = base.load_spec("quadruped")
    floor = next(g for g in spec.geoms if g.name == "floor")
    floor.size = [floor_size, floor_size, 0.5]
    if physics == "tuned":
        base.set_floor_only_contacts(spec, floor="floor")
        base.add_numeric(spec, "max_contact_points", TUNED["max_contact_points"])
    m = spec.compile()
    if physics == "tuned":
        base.tune_solver(m, TUNED["iterations"], TUNED["ls_iterations"], TUNED["eulerdamp"])
    return m


def colored_noise(rng: np.random.Generator, beta: float, steps: int, dims: int) -> np.ndarray:
    """Unit-variance Gaussian noise whose power spectrum falls as 1 / f^beta, per dimension
    ([steps, dims]; beta 0 white, 1 pink, 2 red): the temporally correlated actions of a learned
    policy, for :func:`get_up_trials`."""
    f = np.fft.rfftfreq(steps)
    f[0] = f[1]
    spec = rng.normal(size=(dims, f.size)) + 1j * rng.normal(size=(dims, f.size))
    x = np.fft.irfft(spec * f ** (-beta / 2), n=steps, axis=-1).T
    return x / x.std(0)


def random_drop(m: mujoco.MjModel, d: mujoco.MjData, rng: np.random.Generator) -> float:
    """Reset ``d`` to a uniformly random orientation 0.7 m above the floor, as dm_control's reset
    draws a start, and return the torso's upright (the z component of its z-axis) at the drop."""
    mujoco.mj_resetData(m, d)
    quat = rng.normal(size=4)
    d.qpos[3:7] = quat / np.linalg.norm(quat)
    d.qpos[2] = 0.7
    mujoco.mj_forward(m, d)
    return float(d.xmat[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "torso")][8])


def get_up_trials(
    m: mujoco.MjModel, starts: int, beta: float = 1.0, seed: int = 0
) -> tuple[int, int]:
    """A physics check of a quadruped MjModel's options where quadruped_walk's return is decided:
    from ``starts`` uniformly random orientations (as dm_control's reset draws them, dropped from
    0.7 m) that land down (torso upright < 0.5), colored-noise actions (scale 1, clipped) for 500
    agent steps of 2 control steps, in native MuJoCo. Returns (episodes that got up: upright > 0.8
    after the first 50 agent steps, episodes that went unstable: any of MuJoCo's bad position,
    velocity or acceleration warnings, after which it resets the body to its upright home pose).
    dm_control's options: (0, 0) for the 40 starts of the test and the 60 of envs/assets/README.md."""
    rng = np.random.default_rng(seed)
    d = mujoco.MjData(m)
    torso = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "torso")
    substeps = round(CONTROL_DT / m.opt.timestep)
    w = mujoco.mjtWarning
    warnings = [int(w.mjWARN_BADQPOS), int(w.mjWARN_BADQVEL), int(w.mjWARN_BADQACC)]

    def unstable_count() -> int:
        return sum(d.warning[w].number for w in warnings)

    got_up = unstable = done = 0
    while done < starts:
        upright = random_drop(m, d, rng)
        actions = np.clip(colored_noise(rng, beta, 500, m.nu), -1, 1)
        if upright >= 0.5:
            continue
        done += 1
        warned = unstable_count()
        for k in range(500):
            d.ctrl[:] = actions[k]
            mujoco.mj_step(m, d, nstep=2 * substeps)
            if unstable_count() != warned:  # MuJoCo has reset the data: count, stop
                unstable += 1
                break
            if k > 50 and d.xmat[torso][8] > 0.8:
                got_up += 1
                break
    return got_up, unstable


def _lowest_point(gtype: int, size: np.ndarray, pos: jax.Array, mat: jax.Array) -> jax.Array:
    """Lowest world z of a geom (static type/size; traced pose ``pos [3]``, ``mat [3, 3]``)."""
    if gtype == _GEOM.mjGEOM_SPHERE:
        return pos[2] - size[0]
    if gtype == _GEOM.mjGEOM_CAPSULE:
        return pos[2] - jnp.abs(mat[2, 2]) * size[1] - size[0]
    if gtype == _GEOM.mjGEOM_ELLIPSOID:
        return pos[2] - jnp.sqrt(jnp.sum((mat[2, :] * size[:3]) ** 2))
    if gtype == _GEOM.mjGEOM_CYLINDER:
        az = mat[2, 2]
        return pos[2] - jnp.abs(az) * size[1] - size[0] * jnp.sqrt(jnp.maximum(1 - az**2, 0.0))
    raise ValueError(f"no lowest-point rule for geom type {gtype}")


class QuadrupedMove(base.MjxTask):
    acc_observations = True  # imu accelerometer and toe force/torque sensors

    def __init__(self, desired_speed: float, name: str, physics: str = "tuned"):
        floor_size = DEFAULT_TIME_LIMIT * desired_speed  # dm_control: floor_size=_TIME_LIMIT*speed
        # The reset-height search (like dm_control's) tests every geom that touches the floor in
        # dm_control's model, including geoms the tuned model makes non-colliding.
        self._reset_model = build_model("dmc", floor_size)
        m = build_model(physics, floor_size)
        super().__init__(m, CONTROL_DT, physics)
        self.name = name
        self.desired_speed = desired_speed
        hinges = np.flatnonzero(m.jnt_type == mujoco.mjtJoint.mjJNT_HINGE)
        self._hinge_q = np.asarray(m.jnt_qposadr[hinges])
        self._hinge_v = np.asarray(m.jnt_dofadr[hinges])
        self._torso = base.obj_id(m, "body", "torso")
        self._velocimeter = base.sensor(m, "velocimeter")
        # dm_control orders imu and force/torque sensors by sensor id (np.isin over sensor_type).
        ids = np.arange(m.nsensor)
        imu_types = (mujoco.mjtSensor.mjSENS_GYRO, mujoco.mjtSensor.mjSENS_ACCELEROMETER)
        ft_types = (mujoco.mjtSensor.mjSENS_FORCE, mujoco.mjtSensor.mjSENS_TORQUE)
        self._imu = self._sensor_indices(m, ids[np.isin(m.sensor_type, imu_types)])
        self._force_torque = self._sensor_indices(m, ids[np.isin(m.sensor_type, ft_types)])
        rm = self._reset_model
        floor_id = base.obj_id(rm, "geom", "floor")
        self._height_geoms = [
            (int(g), int(rm.geom_type[g]), rm.geom_size[g].copy())
            for g in range(rm.ngeom)
            if g != floor_id
            and (
                rm.geom_contype[g] & rm.geom_conaffinity[floor_id]
                or rm.geom_conaffinity[g] & rm.geom_contype[floor_id]
            )
        ]
        self._mjx_reset_model = mjx.put_model(rm, impl="jax", device=jax.local_devices()[0])

    @staticmethod
    def _sensor_indices(m: mujoco.MjModel, sensor_ids: np.ndarray) -> jax.Array:
        idx = [np.arange(m.sensor_adr[i], m.sensor_adr[i] + m.sensor_dim[i]) for i in sensor_ids]
        return jnp.asarray(np.concatenate(idx))

    def _initial(self, key):
        m = self.mj_model
        quat = jax.random.normal(key, (4,))
        quat = quat / jnp.linalg.norm(quat)
        qpos = jnp.zeros(m.nq).at[3:7].set(quat)
        z = self._non_contacting_height(qpos)
        qpos = qpos.at[2].set(z)
        return self._data_at(qpos, jnp.zeros(m.nv), jnp.zeros(m.na)), {}

    def _non_contacting_height(self, qpos: jax.Array) -> jax.Array:
        """dm_control's ``_find_non_contacting_height`` in closed form: the first height on the
        1 cm grid (from 0) at which no geom reaches below the floor plane (z = 0)."""
        rm = self._mjx_reset_model
        d = mjx.make_data(rm).replace(qpos=qpos)
        d = mjx.kinematics(rm, d)
        lowest = jnp.stack(
            [
                _lowest_point(t, size, d.geom_xpos[g], d.geom_xmat[g])
                for g, t, size in self._height_geoms
            ]
        ).min()
        steps = jnp.maximum(jnp.ceil(-lowest / HEIGHT_STEP), 0.0)
        return steps * HEIGHT_STEP

    def _observe(self, data, info):
        ego = jnp.concatenate([data.qpos[self._hinge_q], data.qvel[self._hinge_v], data.act])
        return jnp.concatenate(
            [
                ego,
                data.sensordata[self._velocimeter],
                data.xmat[self._torso, 2, 2][None],
                data.sensordata[self._imu],
                jnp.arcsinh(data.sensordata[self._force_torque]),
            ]
        ).astype(jnp.float32)

    def _reward(self, data, info):
        upright = tolerance(
            data.xmat[self._torso, 2, 2],
            (1.0, np.inf),
            margin=2.0,
            value_at_margin=0.0,
            sigmoid="linear",
        )
        s = self.desired_speed
        move = tolerance(
            data.sensordata[self._velocimeter][0],
            (s, np.inf),
            margin=s,
            value_at_margin=0.5,
            sigmoid="linear",
        )
        return upright * move

    def eval_signals(self, data):
        return {"upright": data.xmat[..., self._torso, 2, 2]}

    def eval_metrics(self, signals, returns):
        """How the episodes started, whether the down ones got up and whether the ones on their
        feet stayed there: a start is on its feet when the torso's upright (the z component of its
        z-axis) is >= 0.5 at reset, and an episode ended up when its upright averaged > 0.8 over
        the last 100 agent steps (the classes of ``benchmarks/probe_quadruped.py``). The walk pays
        ~0 on the back, so a return is mostly the number of starts on their feet until an agent
        learns to get up, and the number that fell."""
        u = signals["upright"]  # [steps + 1, episodes]
        on_feet = u[0] >= START_ON_FEET
        ended_up = u[-ENDED_UP_STEPS:].mean(0) > ENDED_UP
        down = ~on_feet

        def mean_of(mask):
            n = mask.sum()
            return jnp.where(
                n > 0, jnp.sum(jnp.where(mask, returns, 0.0)) / jnp.maximum(n, 1), jnp.nan
            )

        return {
            "starts_on_feet": on_feet.sum().astype(jnp.float32),
            "got_up": (down & ended_up).sum().astype(jnp.float32),
            # on its feet at reset, not at the end: mostly the agent toppled itself (the default's
            # runs flipped onto their backs, docs/EXPERIMENTS.md), rarely a start counted on its
            # feet that landed on its side
            "fell": (on_feet & ~ended_up).sum().astype(jnp.float32),
            "return_on_feet": mean_of(on_feet),
            "return_down": mean_of(down),
        }


def quadruped_walk(physics: str = "tuned") -> QuadrupedMove:
    return QuadrupedMove(WALK_SPEED, "quadruped_walk", physics)


def quadruped_run(physics: str = "tuned") -> QuadrupedMove:
    return QuadrupedMove(RUN_SPEED, "quadruped_run", physics)

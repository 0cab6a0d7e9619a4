"""Shared base for the MJX ports of dm_control tasks (brax ``Env`` API, stepping MJX directly).

Semantics follow dm_control (``dm_control/rl/control.py``, ``dm_control/mujoco/engine.py``):

* one control step = ``n_substeps`` physics steps with the action held in ``ctrl``, clamped to the
  actuator ``ctrlrange`` (dm_control copies the raw action into ``ctrl`` and MuJoCo clamps it);
* observations and rewards are computed on the post-step state, as dm_control's ``legacy_step``
  does (``mj_step2``, ``mj_step`` x (n-1), ``mj_step1``): each substep here is ``stage2`` then
  ``stage1`` (see :func:`substep`), so the carried ``mjx.Data`` always has its position/velocity
  stages current, and acceleration-stage sensors hold the last substep's values, as in dm_control
  (raw ``mjx.step`` computes kinematics *before* integrating and would lag one substep);
* no task termination: ``done`` is set only when the physics produced non-finite numbers, flagged in
  ``metrics["nan"]`` (the episode limit is a wrapper, see :mod:`envs.wrappers`).
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from brax.envs.base import Env, State
from mujoco import mjx

from envs import pipeline

ASSETS = Path(__file__).resolve().parent / "assets"

# Physics option sets: "dmc" reproduces dm_control's XML exactly; "tuned" is the per-task set of
# changes measured to leave the task unchanged (see envs/assets/README.md for the evidence).
PHYSICS = ("dmc", "tuned")


def load_spec(name: str) -> mujoco.MjSpec:
    """MjSpec of ``envs/assets/<name>.xml`` (includes resolved relative to the assets folder)."""
    return mujoco.MjSpec.from_file(str(ASSETS / f"{name}.xml"))


def set_floor_only_contacts(spec: mujoco.MjSpec, floor: str, keep: tuple[str, ...] = ()) -> None:
    """Prune collisions to floor-vs-body pairs: bodies collide with the floor, not with each other.

    The floor gets contype 1 / conaffinity 2, every other geom contype 2 / conaffinity 1, so a pair
    collides iff it is (floor, body). Geoms not in ``keep`` (if given) are made non-colliding.
    """
    for g in spec.geoms:
        if g.name == floor:
            g.contype, g.conaffinity = 1, 2
        elif keep and g.name not in keep:
            g.contype, g.conaffinity = 0, 0
        else:
            g.contype, g.conaffinity = 2, 1


def add_numeric(spec: mujoco.MjSpec, name: str, value: int) -> None:
    """Add an MJX collision numeric (``max_contact_points`` / ``max_geom_pairs``)."""
    spec.add_numeric(name=name, data=[float(value)])


def tune_solver(m: mujoco.MjModel, iterations: int, ls_iterations: int, eulerdamp: bool) -> None:
    m.opt.iterations = iterations
    m.opt.ls_iterations = ls_iterations
    if not eulerdamp:
        m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_EULERDAMP)


def stage1(m: mjx.Model, d: mjx.Data) -> mjx.Data:
    """MuJoCo's ``mj_step1``: position and velocity stages (kinematics, COM, collisions,
    constraint rows, transmission, passive and bias forces) and position/velocity sensors."""
    d = pipeline.fwd_position(m, d)
    d = mjx.sensor_pos(m, d)
    d = pipeline.fwd_velocity(m, d)
    d = mjx.sensor_vel(m, d)
    return d


def stage2(m: mjx.Model, d: mjx.Data, integrate: bool = True) -> mjx.Data:
    """MuJoCo's ``mj_step2``: actuation, smooth acceleration, constraint solve, acceleration
    sensors and (with ``integrate``) the semi-implicit Euler step. Needs ``stage1`` done on ``d``."""
    d = mjx.fwd_actuation(m, d)
    d = mjx.fwd_acceleration(m, d)
    if d._impl.efc_J.size == 0:
        d = d.replace(qacc=d.qacc_smooth)
    else:
        d = mjx.solve(m, d)
    d = mjx.sensor_acc(m, d)
    if integrate:
        d = mjx.euler(m, d)
    return d


def substep(m: mjx.Model, d: mjx.Data) -> mjx.Data:
    """One physics step as dm_control's ``legacy_step`` sequences it: ``mj_step2`` on a state whose
    stage 1 is current, then ``mj_step1`` on the integrated state, so observations read off the
    result are up to date (raw ``mjx.step`` would lag one substep)."""
    return stage1(m, stage2(m, d))


def sensor(m: mujoco.MjModel, name: str) -> slice:
    """Slice of ``sensordata`` for the named sensor."""
    i = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SENSOR, name)
    if i < 0:
        raise KeyError(f"sensor {name!r} not in model")
    adr, dim = int(m.sensor_adr[i]), int(m.sensor_dim[i])
    return slice(adr, adr + dim)


def obj_id(m: mujoco.MjModel, kind: str, name: str) -> int:
    objtype = {
        "body": mujoco.mjtObj.mjOBJ_BODY,
        "geom": mujoco.mjtObj.mjOBJ_GEOM,
        "joint": mujoco.mjtObj.mjOBJ_JOINT,
        "site": mujoco.mjtObj.mjOBJ_SITE,
    }[kind]
    i = mujoco.mj_name2id(m, objtype, name)
    if i < 0:
        raise KeyError(f"{kind} {name!r} not in model")
    return i


class MjxTask(Env):
    """A dm_control task on MJX. Subclasses build the model and define the task functions.

    Subclass contract:
      * ``__init__`` builds ``mj_model`` and calls ``super().__init__(mj_model, control_dt, ...)``;
      * ``_initial(key) -> (data, info)`` samples dm_control's reset distribution and returns
        stage-1 data (``self._data_at(qpos, qvel, act)``) and task state (e.g. reacher target);
      * ``_observe(data, info) -> obs [obs_size] float32`` and ``_reward(data, info) -> scalar``.
    """

    name: str = "task"
    acc_observations: bool = False  # observes accelerometer / force / torque sensors

    def __init__(
        self,
        mj_model: mujoco.MjModel,
        control_dt: float,
        physics: str,
    ):
        if physics not in PHYSICS:
            raise ValueError(f"unknown physics {physics!r}; choose one of {PHYSICS}")
        self.physics = physics
        self.mj_model = mj_model
        # On this process's device: MJX's default is jax.devices()[0], which in a multi-process
        # run (jax.distributed) belongs to process 0 and cannot be used as a constant elsewhere.
        device = jax.local_devices()[0]
        self.mjx_model = mjx.put_model(mj_model, impl="jax", device=device)
        self.n_substeps = int(round(control_dt / mj_model.opt.timestep))
        self._dt = control_dt
        if mj_model.opt.integrator != mujoco.mjtIntegrator.mjINT_EULER:
            raise ValueError("dm_control's tasks use the Euler integrator")
        # dm_control's reset ends with mj_forward under disabled actuation; only tasks that
        # observe acceleration-stage sensors need that second stage at reset.
        reset_model = copy.copy(mj_model) if self.acc_observations else None
        if reset_model is not None:
            reset_model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_ACTUATION)
            self._mjx_reset_model = mjx.put_model(reset_model, impl="jax", device=device)
        # The physics stages as jitted closures with one identity per env: every call site
        # (reset's stage 1, cheetah's settling scan, the step's substep scan, the trainer's
        # auto-reset and evaluation) reuses one trace from JAX's cache instead of re-tracing
        # MJX's Python, about 3-5 s per site on 2 cores. XLA inlines the nested calls, so the
        # compiled program is the same.
        model = self.mjx_model
        self.stage1 = jax.jit(lambda d: stage1(model, d))
        self.substep = jax.jit(lambda d: self.stage1(stage2(model, d)))
        limited = mj_model.actuator_ctrllimited.astype(bool)
        lo = np.where(limited, mj_model.actuator_ctrlrange[:, 0], -np.inf)
        hi = np.where(limited, mj_model.actuator_ctrlrange[:, 1], np.inf)
        self.action_low = lo.astype(np.float32)
        self.action_high = hi.astype(np.float32)

    # ---- brax Env API -----------------------------------------------------------------------

    @property
    def observation_size(self) -> int:
        return int(jax.eval_shape(self.reset, jax.random.PRNGKey(0)).obs.shape[-1])

    @property
    def action_size(self) -> int:
        return int(self.mj_model.nu)

    @property
    def backend(self) -> str:
        return "mjx"

    @property
    def dt(self) -> float:
        """Control timestep in seconds."""
        return self._dt

    def reset(self, rng: jax.Array) -> State:
        data, info = self._initial(rng)
        return self._complete(data, info, actuation=False)

    def step(self, state: State, action: jax.Array) -> State:
        data = state.pipeline_state
        ctrl = jnp.clip(action, self.action_low, self.action_high).astype(data.ctrl.dtype)
        data = data.replace(ctrl=ctrl)

        def body(d, _):
            return self.substep(d), None

        data, _ = jax.lax.scan(body, data, None, length=self.n_substeps)
        return self._finish(state, data, state.info)

    # ---- construction helpers ---------------------------------------------------------------

    def state_from_physics(
        self,
        qpos: jax.Array,
        qvel: jax.Array,
        act: jax.Array | None = None,
        ctrl: jax.Array | None = None,
        **task_state: Any,
    ) -> State:
        """The state a dm_control physics in this configuration corresponds to (after
        ``physics.forward()``): for parity tests and debugging. ``task_state`` holds task fields
        (reacher: ``target_xy``)."""
        info = self._task_info(**task_state)
        return self._state_at(qpos, qvel, act, ctrl, info, actuation=True)

    def _task_info(self, **task_state: Any) -> dict[str, jax.Array]:
        if task_state:
            raise TypeError(f"{self.name} has no task state; got {sorted(task_state)}")
        return {}

    def _data_at(self, qpos, qvel, act=None, ctrl=None) -> mjx.Data:
        """``mjx.Data`` at (qpos, qvel, act) with stage 1 (positions, velocities) computed."""
        m = self.mjx_model
        data = mjx.make_data(m)
        data = data.replace(
            qpos=jnp.asarray(qpos, data.qpos.dtype),
            qvel=jnp.asarray(qvel, data.qvel.dtype),
        )
        if act is not None and self.mj_model.na:
            data = data.replace(act=jnp.asarray(act, data.act.dtype))
        if ctrl is not None:
            data = data.replace(ctrl=jnp.asarray(ctrl, data.ctrl.dtype))
        return self.stage1(data)

    def _state_at(self, qpos, qvel, act, ctrl, info, actuation: bool) -> State:
        return self._complete(self._data_at(qpos, qvel, act, ctrl), info, actuation)

    def _complete(self, data: mjx.Data, info: dict, actuation: bool) -> State:
        """First ``State`` from stage-1 data (adding the acceleration stage if observed)."""
        if self.acc_observations:
            # mj_forward's acceleration stage (dm_control disables actuation for it at reset).
            m = self.mjx_model if actuation else self._mjx_reset_model
            data = stage2(m, data, integrate=False)
        return self._first_state(data, info)

    def _first_state(self, data: mjx.Data, info: dict) -> State:
        zero = jnp.zeros((), jnp.float32)
        state = State(
            pipeline_state=data,
            obs=self._observe(data, info),
            reward=zero,
            done=zero,
            metrics={"nan": zero},
            info=dict(info),
        )
        return state

    def _finish(self, state: State, data: mjx.Data, info: dict) -> State:
        finite = jnp.all(jnp.isfinite(data.qpos)) & jnp.all(jnp.isfinite(data.qvel))
        if self.mj_model.na:
            finite &= jnp.all(jnp.isfinite(data.act))
        obs = self._observe(data, info)
        reward = self._reward(data, info)
        nan = (~finite).astype(jnp.float32)
        # Keep downstream numbers finite: a NaN step ends the episode (done) and is flagged.
        obs = jnp.where(finite, obs, 0.0)
        reward = jnp.where(finite, reward, 0.0)
        metrics = dict(state.metrics)
        metrics["nan"] = nan
        return state.replace(
            pipeline_state=data,
            obs=obs.astype(jnp.float32),
            reward=reward.astype(jnp.float32),
            done=nan,
            metrics=metrics,
        )

    def eval_signals(self, data: mjx.Data) -> dict[str, jax.Array]:
        """Per-step quantities an evaluation records for :meth:`eval_metrics` (none by default;
        quadruped: its torso's upright). ``data`` may carry a leading batch axis."""
        del data
        return {}

    def eval_metrics(self, signals: dict[str, jax.Array], returns: jax.Array) -> dict:
        """Task facts of one evaluation, logged beside its return as ``eval/<name>``: scalars from
        ``signals`` (each ``[steps + 1, episodes]``, the reset state first) and the episodes'
        ``returns``. None by default; quadruped counts its starts on their feet and the down
        starts that got up, which its return depends on (docs/EXPERIMENTS.md)."""
        del signals, returns
        return {}

    def render_geom_xpos(self, data: mjx.Data, info: dict) -> jax.Array:
        """Geom positions to draw (``envs.render``): the physics' own, unless the task keeps part of
        its scene outside the model (reacher's target)."""
        del info
        return data.geom_xpos

    # ---- subclass hooks ---------------------------------------------------------------------

    def _initial(self, key: jax.Array):
        raise NotImplementedError

    def _observe(self, data: mjx.Data, info: dict) -> jax.Array:
        raise NotImplementedError

    def _reward(self, data: mjx.Data, info: dict) -> jax.Array:
        raise NotImplementedError


def uniform_limited_hinges(
    key: jax.Array, m: mujoco.MjModel, qpos: jax.Array, unlimited_hinges: bool = True
) -> jax.Array:
    """dm_control's ``randomize_limited_and_rotational_joints`` for hinge/slide joints: limited
    joints ~ U(range), unlimited hinges ~ U(-pi, pi); free/slide roots without limits untouched."""
    hinge, slide = int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)
    lo = np.zeros(m.nq, np.float32)
    hi = np.zeros(m.nq, np.float32)
    mask = np.zeros(m.nq, bool)
    for j in range(m.njnt):
        t, adr = int(m.jnt_type[j]), int(m.jnt_qposadr[j])
        if t not in (hinge, slide):
            continue
        if m.jnt_limited[j]:
            lo[adr], hi[adr], mask[adr] = m.jnt_range[j, 0], m.jnt_range[j, 1], True
        elif t == hinge and unlimited_hinges:
            lo[adr], hi[adr], mask[adr] = -np.pi, np.pi, True
    u = jax.random.uniform(key, (m.nq,), minval=lo, maxval=hi)
    return jnp.where(mask, u, qpos)

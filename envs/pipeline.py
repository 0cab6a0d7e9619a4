"""MJX's position and velocity stages with a fast path for fixed (joint) tendons.

``mjx.fwd_position`` / ``mjx.fwd_velocity`` trace MJX's whole tendon code, spatial wrapping
(site pairs, sphere/cylinder wraps, pulleys, their Jacobians and time derivatives) included, even
when every tendon is a fixed tendon and those arrays are empty. Quadruped's twelve actuator
couplings are fixed tendons, and that dead code was a fifth of the time to trace its step
(benchmarks/bench_envs.py). For a fixed tendon the Jacobian is the constant coefficient matrix and
its time derivative is zero, so here:

* ``ten_length`` is MJX's own segment sum over the joint wraps, ``ten_J`` and the wrap bookkeeping
  are constants built once from the model with numpy (what ``smooth.tendon`` returns for them);
* ``tendon_armature`` is skipped when all tendon armatures are zero (it adds ``J^T 0 J``);
* ``tendon_bias`` is skipped (it adds ``J * armature * (Jdot @ qvel)`` with ``Jdot = 0``).

Models with any other tendon take MJX's functions unchanged. tests/test_pipeline.py checks both
stages against MJX's on a fixed-tendon leg model (CI); on quadruped's own states they are bitwise
equal, and quadruped's parity with dm_control is the slow suite's tests/test_envs_parity.py.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx
from mujoco.mjx._src import collision_driver, constraint, passive, smooth
from mujoco.mjx._src.types import WrapType


def _fixed_tendons(m: mjx.Model) -> dict | None:
    """Constants of a model whose tendons are all fixed, or None (MJX's path)."""
    if not m.ntendon or not np.all(m.wrap_type == WrapType.JOINT):
        return None
    if np.any(m.tendon_adr[1:] != np.cumsum(m.tendon_num)[:-1]) or m.tendon_adr[0] != 0:
        return None  # MJX's indexing below assumes tendons list their wraps in order
    wrap = np.arange(m.nwrap)
    objid = m.wrap_objid[wrap]
    tendon_of_wrap = np.repeat(np.arange(m.ntendon), m.tendon_num)
    ten_J = np.zeros((m.ntendon, m.nv))
    ten_J[tendon_of_wrap, m.jnt_dofadr[objid]] = m.wrap_prm[wrap]
    return {
        "coef": np.asarray(m.wrap_prm[wrap]),
        "qposadr": np.asarray(m.jnt_qposadr[objid]),
        "segments": tendon_of_wrap,
        "ten_J": ten_J,
        "armature": _any_nonzero(m.tendon_armature),
    }


def uses_fixed_tendon_path(m: mjx.Model) -> bool:
    """Whether ``fwd_position`` / ``fwd_velocity`` take the fixed-tendon path for this model."""
    return _fixed_tendons(m) is not None


def _any_nonzero(x) -> bool:
    try:
        return bool(np.any(np.asarray(x)))
    except jax.errors.TracerArrayConversionError:  # model passed as a traced argument
        return True


def _tendon(m: mjx.Model, d: mjx.Data, c: dict) -> mjx.Data:
    length = jax.ops.segment_sum(c["coef"] * d.qpos[c["qposadr"]], c["segments"], m.ntendon)
    impl = d._impl
    return d.tree_replace(
        {
            "ten_length": length.astype(d.ten_length.dtype),
            "_impl.ten_J": jnp.asarray(c["ten_J"], impl.ten_J.dtype),
            "_impl.ten_wrapadr": jnp.zeros(m.ntendon, int),
            "_impl.ten_wrapnum": jnp.zeros(m.ntendon, int),
            "_impl.wrap_xpos": jnp.zeros((m.nwrap, 6), impl.wrap_xpos.dtype),
            "_impl.wrap_obj": jnp.zeros((m.nwrap, 2), int),
        }
    )


def fwd_position(m: mjx.Model, d: mjx.Data) -> mjx.Data:
    """``mjx.fwd_position`` (same stages, same order), fixed tendons without the spatial code."""
    c = _fixed_tendons(m)
    if c is None:
        return mjx.fwd_position(m, d)
    d = smooth.kinematics(m, d)
    d = smooth.com_pos(m, d)
    d = smooth.camlight(m, d)
    d = _tendon(m, d, c)
    d = smooth.crb(m, d)
    if c["armature"]:
        d = smooth.tendon_armature(m, d)
    d = smooth.factor_m(m, d)
    d = collision_driver.collision(m, d)
    d = constraint.make_constraint(m, d)
    d = smooth.transmission(m, d)
    return d


def fwd_velocity(m: mjx.Model, d: mjx.Data) -> mjx.Data:
    """``mjx.fwd_velocity`` (same stages, same order); fixed tendons have no bias term."""
    c = _fixed_tendons(m)
    if c is None:
        return mjx.fwd_velocity(m, d)
    d = d.tree_replace(
        {
            "_impl.actuator_velocity": d._impl.actuator_moment @ d.qvel,
            "_impl.ten_velocity": d._impl.ten_J @ d.qvel,
        }
    )
    d = smooth.com_vel(m, d)
    d = passive.passive(m, d)
    d = smooth.rne(m, d)
    return d

"""envs.pipeline's fixed-tendon fast path computes what MJX's own stages compute.

A small model shaped like one quadruped leg (free root, three hinges, fixed coupling tendons, an
actuator on a tendon, a floor contact) keeps the compile short; quadruped itself is checked
against dm_control end to end in tests/test_envs_parity.py (slow suite).
"""

from __future__ import annotations

import jax
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from envs import pipeline

LEG = """
<mujoco>
  <option timestep="0.005"/>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 .1"/>
    <body name="torso" pos="0 0 .6">
      <freejoint/>
      <geom type="ellipsoid" size=".2 .1 .08" mass="2"/>
      <body name="thigh" pos=".1 0 0">
        <joint name="hip" axis="0 1 0" range="-60 60" damping="1"/>
        <geom type="capsule" fromto="0 0 0 0 0 -.2" size=".03"/>
        <body name="shin" pos="0 0 -.2">
          <joint name="knee" axis="0 1 0" range="-120 0" damping="1"/>
          <geom type="capsule" fromto="0 0 0 0 0 -.2" size=".025"/>
          <body name="foot" pos="0 0 -.2">
            <joint name="ankle" axis="1 0 0" range="-40 40" damping="1"/>
            <geom type="sphere" size=".03"/>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
  <tendon>
    <fixed name="coupling"{armature}>
      <joint joint="hip" coef=".333"/> <joint joint="knee" coef=".333"/>
      <joint joint="ankle" coef=".333"/>
    </fixed>
    <fixed name="lift" stiffness="3" damping=".5">
      <joint joint="hip" coef=".5"/> <joint joint="ankle" coef="-.5"/>
    </fixed>
  </tendon>
  <actuator>
    <general tendon="lift" gainprm="20" ctrlrange="-1 1" ctrllimited="true"/>
    <general joint="knee" gainprm="10" ctrlrange="-1 1" ctrllimited="true"/>
  </actuator>
</mujoco>
"""


def _random_data(m: mjx.Model, mj: mujoco.MjModel, key: jax.Array, n: int) -> mjx.Data:
    kq, kv, ku = jax.random.split(key, 3)
    qpos = np.tile(mj.qpos0, (n, 1))
    qpos[:, 2] = np.asarray(jax.random.uniform(kq, (n,), minval=0.2, maxval=0.8))
    qpos[:, 7:] = np.asarray(jax.random.uniform(kq, (n, mj.nq - 7), minval=-0.7, maxval=0.7))
    qvel = np.asarray(jax.random.normal(kv, (n, mj.nv)))
    ctrl = np.asarray(jax.random.uniform(ku, (n, mj.nu), minval=-1, maxval=1))
    d0 = mjx.make_data(m)
    return jax.vmap(lambda q, v, u: d0.replace(qpos=q, qvel=v, ctrl=u))(qpos, qvel, ctrl)


@pytest.mark.parametrize("armature", [0.0, 0.05])
def test_fixed_tendon_stages_equal_mjx(armature):
    xml = LEG.format(armature=f' armature="{armature}"' if armature else "")
    mj = mujoco.MjModel.from_xml_string(xml)
    m = mjx.put_model(mj, impl="jax")
    assert pipeline.uses_fixed_tendon_path(m)
    d = _random_data(m, mj, jax.random.PRNGKey(0), 16)

    def both(d):
        ours = pipeline.fwd_velocity(m, pipeline.fwd_position(m, d))
        theirs = mjx.fwd_velocity(m, mjx.fwd_position(m, d))
        return ours, theirs

    ours, theirs = jax.jit(jax.vmap(both))(d)
    assert np.all(np.isfinite(np.asarray(ours.qfrc_bias)))
    assert np.any(np.asarray(ours.ten_length) != 0) and np.any(np.asarray(ours.ncon) > 0)
    paths = jax.tree_util.tree_leaves_with_path(theirs)
    for (path, want), got in zip(paths, jax.tree.leaves(ours), strict=True):
        name = jax.tree_util.keystr(path)
        assert got.shape == want.shape and got.dtype == want.dtype, name
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6, err_msg=name)


def test_other_tendons_take_mjx_path():
    xml = LEG.format(armature="").replace(
        '<fixed name="lift"',
        '<spatial name="s"><site site="a"/><site site="b"/></spatial><fixed name="lift"',
    )
    xml = xml.replace(
        '<geom type="sphere" size=".03"/>', '<geom type="sphere" size=".03"/><site name="b"/>'
    ).replace("<freejoint/>", '<freejoint/><site name="a"/>')
    mj = mujoco.MjModel.from_xml_string(xml)
    assert not pipeline.uses_fixed_tendon_path(mjx.put_model(mj, impl="jax"))
    no_tendon = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><body><joint/><geom size='.1'/></body></worldbody></mujoco>"
    )
    assert not pipeline.uses_fixed_tendon_path(mjx.put_model(no_tendon, impl="jax"))

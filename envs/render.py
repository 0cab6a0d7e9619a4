"""CPU video frames without OpenGL: a pinhole ray caster on ``mjx.ray`` (jitted, vmapped).

MuJoCo's own renderer needs an OpenGL context (EGL/OSMesa), which CPU servers often lack; this one
runs wherever JAX runs. Colours come from geom/material RGBA with Lambert shading (normals from the
depth image), a checkerboard floor and a sky gradient. ``mjx.ray`` has no cylinder support, so
cylinders (reacher's base, quadruped's eyes) are not drawn.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

# Cameras used for pixels by Dreamer/LatCo (D1/LC wrappers, D2 envs.py): camera id per domain.
CAMERAS = {"cheetah": 0, "reacher": 0, "quadruped": 2, "walker": 0}


def _geom_rgb(m: mujoco.MjModel) -> np.ndarray:
    rgb = m.geom_rgba[:, :3].copy()
    has_mat = m.geom_matid >= 0
    rgb[has_mat] = m.mat_rgba[m.geom_matid[has_mat], :3]
    return rgb.astype(np.float32)


def make_renderer(env, width: int = 128, height: int = 128, camera: int | None = None):
    """Returns ``render(qpos [nq], target_xy [2] | None) -> uint8 [H, W, 3]`` (jittable)."""
    mj = env.mj_model
    domain = env.name.split("_")[0]
    cam = CAMERAS.get(domain, 0) if camera is None else camera
    if mj.ncam <= cam:
        raise ValueError(f"{env.name} has {mj.ncam} cameras; no camera {cam}")
    m = mjx.put_model(mj, impl="jax")
    rgb = jnp.asarray(_geom_rgb(mj))
    planes = jnp.asarray(mj.geom_type == mujoco.mjtGeom.mjGEOM_PLANE)
    target = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_GEOM, "target")
    fovy = float(mj.cam_fovy[cam])
    tan = np.tan(np.deg2rad(fovy) / 2)
    j, i = np.meshgrid(np.arange(width), np.arange(height))
    u = ((j + 0.5) / width * 2 - 1) * tan * width / height
    v = (1 - (i + 0.5) / height * 2) * tan
    dirs_cam = jnp.asarray(np.stack([u, v, -np.ones_like(u)], -1).reshape(-1, 3), jnp.float32)

    def render(qpos: jax.Array, target_xy: jax.Array | None = None) -> jax.Array:
        model = m
        if target_xy is not None and target >= 0:
            model = m.replace(geom_pos=m.geom_pos.at[target, :2].set(target_xy))
        d = mjx.make_data(model).replace(qpos=qpos)
        d = mjx.kinematics(model, d)
        d = mjx.com_pos(model, d)
        d = mjx.camlight(model, d)
        origin = d.cam_xpos[cam]
        dirs = dirs_cam @ d.cam_xmat[cam].T
        dirs = dirs / jnp.linalg.norm(dirs, axis=-1, keepdims=True)
        dist, geom = jax.vmap(lambda v: mjx.ray(model, d, origin, v))(dirs)
        hit = geom >= 0
        dist = jnp.where(hit, dist, 1e3)
        points = origin + dirs * dist[:, None]
        depth = dist.reshape(height, width)
        pts = points.reshape(height, width, 3)
        # normals from the depth image (cross product of neighbouring hit points)
        dx = jnp.gradient(pts, axis=1)
        dy = jnp.gradient(pts, axis=0)
        normal = jnp.cross(dx, dy)
        normal = normal / (jnp.linalg.norm(normal, axis=-1, keepdims=True) + 1e-9)
        normal = jnp.where(
            jnp.sum(normal * dirs.reshape(height, width, 3), -1, keepdims=True) > 0, -normal, normal
        )
        light = jnp.array([0.3, -0.4, 0.85]) / jnp.linalg.norm(jnp.array([0.3, -0.4, 0.85]))
        lambert = 0.35 + 0.65 * jnp.clip(jnp.sum(normal * light, -1), 0.0, 1.0)
        g = jnp.maximum(geom, 0).reshape(height, width)
        base = rgb[g]
        checker = (jnp.floor(pts[..., 0] * 2) + jnp.floor(pts[..., 1] * 2)) % 2
        floor = jnp.where(
            checker[..., None] > 0, jnp.array([0.2, 0.3, 0.4]), jnp.array([0.1, 0.2, 0.3])
        )
        base = jnp.where(planes[g][..., None], floor, base)
        shaded = base * jnp.where(planes[g], 1.0, lambert)[..., None]
        fog = jnp.exp(-0.02 * depth)[..., None]
        sky = jnp.linspace(0.8, 0.35, height)[:, None, None] * jnp.array([0.5, 0.7, 1.0])
        image = jnp.where(
            hit.reshape(height, width)[..., None], shaded * fog + sky * (1 - fog), sky
        )
        return (jnp.clip(image, 0, 1) * 255).astype(jnp.uint8)

    return render


def render_episode(
    env, qpos: np.ndarray, target_xy=None, width: int = 128, height: int = 128, every: int = 1
) -> np.ndarray:
    """Frames ``uint8 [T, H, W, 3]`` for a qpos trajectory ``[T, nq]`` (every ``every``-th)."""
    render = make_renderer(env, width, height)
    t = None if target_xy is None else jnp.asarray(target_xy)
    frames = jax.jit(jax.vmap(lambda q: render(q, t)))(jnp.asarray(qpos[::every]))
    return np.asarray(frames)

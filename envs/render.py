"""Camera images without OpenGL: an analytic ray caster in JAX, fast enough to run in the env step.

MuJoCo's own renderer needs an OpenGL context and runs outside XLA; MJX's batch renderer is GPU-only.
This one casts one ray per pixel against every visible geom with closed-form intersections (plane,
sphere, capsule, ellipsoid, cylinder, box: every type the four domains draw) in each geom's own
frame, so a frame is a few dense array ops that jit, vmap over envs and fuse into the training
program on CPU or GPU. The scene follows MuJoCo's defaults closely enough that a person sees the same
picture (``make preview`` puts the two side by side; tests check body silhouettes against
``mujoco.Renderer``): geom/material colours, the ``grid`` checker floor (0.5 m squares), the
gradient skybox, the model's headlight (ambient + diffuse from the camera) plus the model's first
light as a directional key light. Not drawn: shadows, reflections, specular highlights, the
skybox's random marks, textures other than the floor's checker.

Poses come from ``mjx.Data`` (``geom_xpos/xmat``, ``cam_xpos/xmat``), which the env step has already
computed, so rendering adds no kinematics to the step.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

# Cameras of the pixel benchmarks (Dreamer, DrQ, LatCo): camera id per domain.
CAMERAS = {"cheetah": 0, "reacher": 0, "quadruped": 2, "walker": 0}

_G = mujoco.mjtGeom
_TYPES = ("plane", "sphere", "capsule", "ellipsoid", "cylinder", "box")
_INF = 1e6
# MuJoCo's light diffuse default (the models' lights set none) and the suite's skybox.xml; the
# headlight's ambient and diffuse come from the model (common/visual.xml: 0.4, 0.8).
_KEY_DIFFUSE = 0.5
# The floor's reflectance (0.2) darkens it in MuJoCo's render; matched on mean floor colour.
_FLOOR_GAIN = 0.72
_SKY_TOP, _SKY_BOTTOM = np.array([0.4, 0.6, 0.8]), np.array([0.0, 0.0, 0.0])


class Scene(NamedTuple):
    """Static description of what one camera sees of one model (numpy; closed over when jitted)."""

    width: int
    height: int
    camera: int
    geoms: dict  # type name -> int array of geom ids
    size: np.ndarray  # [ngeom, 3]
    rgb: np.ndarray  # [ngeom, 3]
    checker: np.ndarray  # [ngeom] bool: plane with the suite's 'grid' material
    tiled: np.ndarray  # [ngeom] bool: ... drawn as a checkerboard (else its mean colour)
    checker_rgb: np.ndarray  # [2, 3]
    rays: np.ndarray  # [H*W, 3] unit directions in the camera frame
    key_dir: np.ndarray  # [3] direction the key light shines (world), or zeros
    head: tuple  # (ambient, diffuse) of the model's headlight (grey levels)


def _visible(m: mujoco.MjModel) -> np.ndarray:
    """Geoms MuJoCo draws by default: groups 0-2 with non-zero alpha."""
    alpha = m.geom_rgba[:, 3].copy()
    has_mat = m.geom_matid >= 0
    alpha[has_mat] = m.mat_rgba[m.geom_matid[has_mat], 3]
    return (m.geom_group < 3) & (alpha > 0)


def camera_for(env) -> int:
    """The benchmark camera of an env (by domain: quadruped 2, the others 0)."""
    return CAMERAS.get(env.name.split("_")[0], 0)


def make_scene(m: mujoco.MjModel, width: int = 64, height: int = 64, camera: int = 0) -> Scene:
    if not 0 <= camera < m.ncam:
        raise ValueError(f"the model has {m.ncam} cameras (0..{m.ncam - 1}); no camera {camera}")
    if width < 1 or height < 1:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    vis = _visible(m)
    names = {
        "plane": _G.mjGEOM_PLANE,
        "sphere": _G.mjGEOM_SPHERE,
        "capsule": _G.mjGEOM_CAPSULE,
        "ellipsoid": _G.mjGEOM_ELLIPSOID,
        "cylinder": _G.mjGEOM_CYLINDER,
        "box": _G.mjGEOM_BOX,
    }
    drawn = set()
    geoms = {}
    for name in _TYPES:
        ids = np.flatnonzero(vis & (m.geom_type == names[name]))
        if ids.size:
            geoms[name] = ids
            drawn.update(ids.tolist())
    skipped = sorted(set(np.flatnonzero(vis).tolist()) - drawn)
    if skipped:
        kinds = sorted({_G(int(m.geom_type[i])).name for i in skipped})
        raise ValueError(f"the renderer does not draw geom types {kinds} (geoms {skipped})")
    rgb = m.geom_rgba[:, :3].copy()
    has_mat = m.geom_matid >= 0
    rgb[has_mat] = m.mat_rgba[m.geom_matid[has_mat], :3]
    grid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_MATERIAL, "grid")
    # The 'grid' checker, 0.5 m squares, on planes whose rendering grid spacing (size[2]) is below
    # their half-size; MuJoCo's reacher floor (0.3 m, spacing 10) shows one flat colour.
    checker = (m.geom_matid == grid) & (grid >= 0)
    tiled = checker & (m.geom_size[:, 2] < np.maximum(m.geom_size[:, 0], m.geom_size[:, 1]))
    fovy = float(m.cam_fovy[camera])
    tan = np.tan(np.deg2rad(fovy) / 2)
    j, i = np.meshgrid(np.arange(width), np.arange(height))
    u = ((j + 0.5) / width * 2 - 1) * tan * width / height
    v = (1 - (i + 0.5) / height * 2) * tan
    rays = np.stack([u, v, -np.ones_like(u)], -1).reshape(-1, 3)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    key = np.zeros(3)
    if m.nlight:
        key = m.light_dir[0] / (np.linalg.norm(m.light_dir[0]) + 1e-9)
    return Scene(
        width=width,
        height=height,
        camera=camera,
        geoms=geoms,
        size=m.geom_size.astype(np.float32),
        rgb=rgb.astype(np.float32),
        checker=checker,
        tiled=tiled,
        checker_rgb=np.array([[0.1, 0.2, 0.3], [0.2, 0.3, 0.4]], np.float32),
        rays=rays.astype(np.float32),
        key_dir=key.astype(np.float32),
        head=(float(m.vis.headlight.ambient[0]), float(m.vis.headlight.diffuse[0])),
    )


def _sqrt_or_inf(disc, num_minus, a):
    """Nearest root ``(-b - sqrt(disc)) / a`` of a ray quadratic; +inf where it misses or is behind."""
    t = (num_minus - jnp.sqrt(jnp.maximum(disc, 0.0))) / a
    return jnp.where((disc >= 0) & (t > 1e-6), t, _INF)


def _sphere_t(o, e, r):
    """Ray ``o + t e`` (|e| = 1) against a sphere of radius r at the origin; o [G,3], e [P,G,3]."""
    b = jnp.sum(o * e, -1)
    c = jnp.sum(o * o, -1) - r**2
    return _sqrt_or_inf(b * b - c, -b, 1.0)


def _side_t(o, e, r, h):
    """Against the side of a z-axis cylinder of radius r, half-length h (caps excluded)."""
    a = e[..., 0] ** 2 + e[..., 1] ** 2
    b = o[..., 0] * e[..., 0] + o[..., 1] * e[..., 1]
    c = o[..., 0] ** 2 + o[..., 1] ** 2 - r**2
    a = jnp.maximum(a, 1e-12)
    t = _sqrt_or_inf(b * b - a * c, -b, a)
    z = o[..., 2] + t * e[..., 2]
    return jnp.where(jnp.abs(z) <= h, t, _INF)


def _intersect(kind, o, e, size):
    """Distances [P, G] along unit rays to geoms of one type, in each geom's frame."""
    if kind == "sphere":
        return _sphere_t(o, e, size[:, 0])
    if kind == "ellipsoid":
        o2, e2 = o / size, e / size
        a = jnp.sum(e2 * e2, -1)
        b = jnp.sum(o2 * e2, -1)
        c = jnp.sum(o2 * o2, -1) - 1.0
        return _sqrt_or_inf(b * b - a * c, -b, a)
    if kind == "capsule":
        r, h = size[:, 0], size[:, 1]
        shift = jnp.stack([jnp.zeros_like(h), jnp.zeros_like(h), h], -1)
        t = _side_t(o, e, r, h)
        t = jnp.minimum(t, _sphere_t(o - shift, e, r))
        return jnp.minimum(t, _sphere_t(o + shift, e, r))
    if kind == "cylinder":
        r, h = size[:, 0], size[:, 1]
        t = _side_t(o, e, r, h)
        ez = jnp.where(jnp.abs(e[..., 2]) < 1e-9, 1e-9, e[..., 2])
        for sign in (1.0, -1.0):
            tc = (sign * h - o[..., 2]) / ez
            x = o[..., 0] + tc * e[..., 0]
            y = o[..., 1] + tc * e[..., 1]
            ok = (tc > 1e-6) & (x * x + y * y <= r**2)
            t = jnp.minimum(t, jnp.where(ok, tc, _INF))
        return t
    if kind == "box":
        inv = 1.0 / jnp.where(jnp.abs(e) < 1e-9, 1e-9, e)
        t1 = (-size - o) * inv
        t2 = (size - o) * inv
        near = jnp.max(jnp.minimum(t1, t2), -1)
        far = jnp.min(jnp.maximum(t1, t2), -1)
        return jnp.where((far >= near) & (near > 1e-6), near, _INF)
    if kind == "plane":
        ez = e[..., 2]
        t = -o[..., 2] / jnp.where(jnp.abs(ez) < 1e-9, -1e-9, ez)
        x = o[..., 0] + t * e[..., 0]
        y = o[..., 1] + t * e[..., 1]
        sx, sy = size[:, 0], size[:, 1]
        inside = ((sx <= 0) | (jnp.abs(x) <= sx)) & ((sy <= 0) | (jnp.abs(y) <= sy))
        # drawn from the side its normal faces (a floor is seen from above)
        return jnp.where(inside & (t > 1e-6) & (o[..., 2] > 0), t, _INF)
    raise ValueError(kind)


def _local_normal(kind_of, q, size):
    """Outward normal at local hit point q [P,3] of geom type ``kind_of`` [P] (index in _TYPES)."""
    h = size[:, 1:2]
    cap = jnp.concatenate([q[:, :2], q[:, 2:3] - jnp.clip(q[:, 2:3], -h, h)], -1)
    on_cap = jnp.abs(q[:, 2:3]) >= h - 1e-5 * jnp.maximum(h, 1.0)
    cyl = jnp.where(
        on_cap,
        jnp.concatenate([0 * q[:, :2], jnp.sign(q[:, 2:3])], -1),
        jnp.concatenate([q[:, :2], 0 * q[:, 2:3]], -1),
    )
    rel = jnp.abs(q) / jnp.maximum(size, 1e-9)
    box = jax.nn.one_hot(jnp.argmax(rel, -1), 3) * jnp.sign(q)
    normals = jnp.stack(
        [
            jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0]), q.shape),  # plane
            q,  # sphere
            cap,  # capsule
            q / jnp.maximum(size, 1e-9) ** 2,  # ellipsoid
            cyl,  # cylinder
            box,  # box
        ]
    )
    n = jnp.take_along_axis(normals, kind_of[None, :, None], 0)[0]
    return n / (jnp.linalg.norm(n, axis=-1, keepdims=True) + 1e-9)


def render_pose(scene: Scene, geom_xpos, geom_xmat, cam_pos, cam_mat, with_ids: bool = False):
    """One frame ``uint8 [H, W, 3]`` from world poses (``geom_xmat`` [ngeom, 3, 3] or [ngeom, 9]).

    With ``with_ids`` also the geom id seen at each pixel ``int32 [H, W]`` (-1: sky)."""
    geom_xmat = jnp.reshape(geom_xmat, (-1, 3, 3))
    cam_mat = jnp.reshape(cam_mat, (3, 3))
    dirs = jnp.asarray(scene.rays) @ cam_mat.T  # [P, 3] world
    best_t = jnp.full(dirs.shape[0], _INF)
    best_g = jnp.full(dirs.shape[0], -1, jnp.int32)
    kind_idx = jnp.zeros(dirs.shape[0], jnp.int32)
    for kind, ids in scene.geoms.items():
        rot = geom_xmat[ids]  # [G, 3, 3] local -> world
        o = jnp.einsum("gji,gj->gi", rot, cam_pos[None] - geom_xpos[ids])  # R^T (c - p)
        e = jnp.einsum("pj,gji->pgi", dirs, rot)  # R^T d, [P, G, 3]
        t = _intersect(kind, o[None], e, jnp.asarray(scene.size[ids]))
        j = jnp.argmin(t, -1)
        tj = jnp.min(t, -1)
        closer = tj < best_t
        best_t = jnp.where(closer, tj, best_t)
        best_g = jnp.where(closer, jnp.asarray(ids, jnp.int32)[j], best_g)
        kind_idx = jnp.where(closer, _TYPES.index(kind), kind_idx)
    hit = best_g >= 0
    g = jnp.maximum(best_g, 0)
    point = cam_pos + dirs * jnp.where(hit, best_t, 0.0)[:, None]
    rot = geom_xmat[g]  # [P, 3, 3]
    q = jnp.einsum("pji,pj->pi", rot, point - geom_xpos[g])
    size = jnp.asarray(scene.size)[g]
    normal = jnp.einsum("pij,pj->pi", rot, _local_normal(kind_idx, q, size))
    normal = jnp.where(jnp.sum(normal * dirs, -1, keepdims=True) > 0, -normal, normal)
    base = jnp.asarray(scene.rgb)[g]
    parity = (jnp.floor(q[:, 0] * 2) + jnp.floor(q[:, 1] * 2)) % 2
    checks = jnp.asarray(scene.checker_rgb)
    floor = jnp.where(
        jnp.asarray(scene.tiled)[g][:, None], checks[parity.astype(jnp.int32)], checks.mean(0)
    )
    base = jnp.where(jnp.asarray(scene.checker)[g][:, None], floor * _FLOOR_GAIN, base)
    head = jnp.clip(-jnp.sum(normal * dirs, -1), 0.0, 1.0)
    key = jnp.clip(-normal @ jnp.asarray(scene.key_dir), 0.0, 1.0)
    light = scene.head[0] + scene.head[1] * head + _KEY_DIFFUSE * key
    shaded = base * light[:, None]
    w = jnp.clip(dirs[:, 2] * 0.5 + 0.5, 0.0, 1.0)[:, None]
    sky = jnp.asarray(_SKY_BOTTOM, jnp.float32) + w * jnp.asarray(
        _SKY_TOP - _SKY_BOTTOM, jnp.float32
    )
    image = jnp.where(hit[:, None], shaded, sky)
    image = (jnp.clip(image, 0.0, 1.0) * 255 + 0.5).astype(jnp.uint8)
    image = image.reshape(scene.height, scene.width, 3)
    if with_ids:
        return image, best_g.reshape(scene.height, scene.width)
    return image


def render_data(scene: Scene, data: mjx.Data, geom_xpos=None, with_ids: bool = False):
    """A frame of ``data`` (positions computed), optionally with overridden geom positions."""
    xpos = data.geom_xpos if geom_xpos is None else geom_xpos
    return render_pose(
        scene,
        xpos,
        data.geom_xmat,
        data.cam_xpos[scene.camera],
        data.cam_xmat[scene.camera],
        with_ids,
    )


def pose_renderer(env, size: int = 64):
    """Jitted ``(qpos [nq], target_xy [2] | None) -> (uint8 [size, size, 3], geom ids [size, size])``
    of a bare task posed at ``qpos`` with zero velocities, through the task's own state (stage 1
    of the physics) and its ``render_geom_xpos``: for tests and comparisons."""
    scene = make_scene(env.mj_model, size, size, camera_for(env))

    @jax.jit
    def frame(qpos, target_xy):
        task = {} if target_xy is None else {"target_xy": target_xy}
        state = env.state_from_physics(qpos, jnp.zeros(env.mj_model.nv), **task)
        d = state.pipeline_state
        return render_data(scene, d, env.render_geom_xpos(d, state.info), with_ids=True)

    return frame


def make_renderer(env, width: int = 128, height: int = 128, camera: int | None = None):
    """Returns ``render(qpos [nq], target_xy [2] | None) -> uint8 [H, W, 3]`` (jittable)."""
    scene = make_scene(env.mj_model, width, height, camera_for(env) if camera is None else camera)
    m = mjx.put_model(env.mj_model, impl="jax")

    def render(qpos: jax.Array, target_xy: jax.Array | None = None) -> jax.Array:
        d = mjx.make_data(m).replace(qpos=qpos)
        d = mjx.kinematics(m, d)
        d = mjx.com_pos(m, d)
        d = mjx.camlight(m, d)
        info = {} if target_xy is None else {"target_xy": target_xy}
        return render_data(scene, d, env.render_geom_xpos(d, info))

    return render


def render_episode(
    env, qpos: np.ndarray, target_xy=None, width: int = 128, height: int = 128, every: int = 1
) -> np.ndarray:
    """Frames ``uint8 [T, H, W, 3]`` for a qpos trajectory ``[T, nq]`` (every ``every``-th)."""
    render = make_renderer(env, width, height)
    t = None if target_xy is None else jnp.asarray(target_xy)
    frames = jax.jit(jax.vmap(lambda q: render(q, t)))(jnp.asarray(qpos[::every]))
    return np.asarray(frames)

"""Our frames against MuJoCo's own renderer on the same states: silhouette IoU and a preview grid.

``python -m envs.reference cheetah_run [--out preview.png] [--states 6] [--size 64]`` renders states
from a random rollout with both renderers, prints the IoU of the body silhouettes per state and
writes a PNG grid (ours | MuJoCo's | masks) for a person to look at. MuJoCo's renderer needs an
OpenGL context: this module sets ``MUJOCO_GL=osmesa`` (software, Debian's ``libosmesa6``, which
``make install`` installs) unless ``MUJOCO_GL`` is already set, so import it before ``mujoco`` or run it
as a program. ``make preview ENV=<task|all>`` runs it.

The silhouette of "the bodies" is every drawn pixel that is not a plane (floor, walls) or sky:
the robot's geoms and, in reacher, the target and the arm's base.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")

import argparse  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

import envs  # noqa: E402
from envs import render  # noqa: E402


class NoOpenGL(RuntimeError):
    """MuJoCo's renderer could not get an OpenGL context here."""


def rollout_states(task: str, n: int, seed: int = 0, steps: int = 30):
    """``n`` states (qpos, target_xy or None), each from its own episode (reset with key
    ``seed + i``) after ``steps`` random-action control steps, so bodies have moved off their
    rest pose and reacher's target differs between states."""
    env = envs.make(task, normalize_actions=True)

    @jax.jit
    def episode(key):
        k_reset, k_act = jax.random.split(key)
        actions = jax.random.uniform(k_act, (steps, env.action_size), minval=-1, maxval=1)
        state, _ = jax.lax.scan(lambda s, a: (env.step(s, a), None), env.reset(k_reset), actions)
        return state.pipeline_state.qpos, state.info.get("target_xy")

    out = []
    for i in range(n):
        qpos, target = episode(jax.random.PRNGKey(seed + i))
        out.append((np.asarray(qpos), None if target is None else np.asarray(target)))
    return env.unwrapped if hasattr(env, "unwrapped") else env, out


def mujoco_frames(env, states, size: int):
    """MuJoCo's render and geom-id image of each state (raises NoOpenGL without a GL context)."""
    m = env.mj_model
    cam = render.camera_for(env)
    target = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "target")
    target_pos = m.geom_pos[target].copy() if target >= 0 else None
    d = mujoco.MjData(m)
    try:
        r = mujoco.Renderer(m, size, size)
    except Exception as e:  # noqa: BLE001 - any GL failure means: no reference here
        raise NoOpenGL(
            f"MuJoCo's renderer has no OpenGL context (MUJOCO_GL={os.environ.get('MUJOCO_GL')}): {e}"
        ) from e
    images, ids = [], []
    try:
        for qpos, txy in states:
            if txy is not None:
                m.geom_pos[target, :2] = txy
            d.qpos[:] = qpos
            mujoco.mj_forward(m, d)
            r.disable_segmentation_rendering()
            r.update_scene(d, camera=cam)
            images.append(r.render().copy())
            r.enable_segmentation_rendering()
            r.update_scene(d, camera=cam)
            seg = r.render()
            ids.append(np.where(seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM), seg[..., 0], -1))
    finally:
        r.close()
        if target_pos is not None:
            m.geom_pos[target] = target_pos
    return np.stack(images), np.stack(ids)


def our_frames(env, states, size: int):
    """Our render and geom-id image of each state."""
    one = render.pose_renderer(env, size)
    images, ids = [], []
    for qpos, txy in states:
        im, g = one(jnp.asarray(qpos), None if txy is None else jnp.asarray(txy))
        images.append(np.asarray(im))
        ids.append(np.asarray(g))
    return np.stack(images), np.stack(ids)


def body_mask(env, ids: np.ndarray) -> np.ndarray:
    """Pixels showing a geom that is not a plane."""
    planes = env.mj_model.geom_type == mujoco.mjtGeom.mjGEOM_PLANE
    return (ids >= 0) & ~planes[np.maximum(ids, 0)]


def iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Intersection over union per image of two boolean masks [N, H, W]."""
    inter = (a & b).sum((-1, -2))
    union = (a | b).sum((-1, -2))
    return np.where(union > 0, inter / np.maximum(union, 1), 1.0)


def compare(task: str, n: int = 6, size: int = 64, seed: int = 0):
    """(ours, theirs, ours_mask, their_mask, iou per state) for ``n`` rollout states of ``task``."""
    env, states = rollout_states(task, n, seed)
    theirs, their_ids = mujoco_frames(env, states, size)
    ours, our_ids = our_frames(env, states, size)
    a, b = body_mask(env, our_ids), body_mask(env, their_ids)
    return ours, theirs, a, b, iou(a, b)


def grid_png(rows, path: Path, scale: int = 3) -> None:
    """Writes rows of [ours | MuJoCo | mask overlap] tiles, upscaled ``scale`` x, as one PNG."""
    from PIL import Image

    tiles = []
    for ours, theirs, a, b in rows:
        overlap = np.zeros(ours.shape, np.uint8)
        overlap[a & b] = (255, 255, 255)
        overlap[a & ~b] = (255, 80, 80)  # ours only: red
        overlap[~a & b] = (80, 160, 255)  # MuJoCo only: blue
        gap = np.full((ours.shape[0], 2, 3), 255, np.uint8)
        tiles.append(np.concatenate([ours, gap, theirs, gap, overlap], 1))
    image = np.concatenate(
        [np.concatenate([t, np.full((2, t.shape[1], 3), 255, np.uint8)], 0) for t in tiles], 0
    )
    Image.fromarray(image).resize(
        (image.shape[1] * scale, image.shape[0] * scale), Image.NEAREST
    ).save(path)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("task", help="a task name, or 'all'")
    p.add_argument("--states", type=int, default=6)
    p.add_argument("--size", type=int, default=64)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="preview", help="folder for <task>.png")
    args = p.parse_args(argv)
    tasks = envs.registered() if args.task == "all" else [envs.canonical(args.task)]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for task in tasks:
        try:
            ours, theirs, a, b, scores = compare(task, args.states, args.size, args.seed)
        except NoOpenGL as e:
            print(f"{task}: {e}", file=sys.stderr)
            return 1
        path = out / f"{task}.png"
        grid_png(list(zip(ours, theirs, a, b, strict=True)), path)
        print(
            f"{task}: body silhouette IoU against MuJoCo's renderer "
            f"min {scores.min():.3f} mean {scores.mean():.3f} over {len(scores)} states "
            f"(ours | MuJoCo | overlap: white both, red ours only, blue MuJoCo only) -> {path}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())

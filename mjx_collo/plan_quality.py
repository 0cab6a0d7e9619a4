"""Planner quality on a trained world model: the measure behind ``make bench-plan-quality`` and
the planner-quality tests.

Random-weight models hide a planner that does not plan, so planner defaults are judged on a
trained world model (``benchmarks/fixtures``: the world model and a replay slice of a CEM cheetah
run) from posterior contexts filtered along that run's replay.
"""

from __future__ import annotations

import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from mjx_collo import agent as agent_lib
from mjx_collo import config
from mjx_collo import world_model as wm_lib
from mjx_collo.flops import matmul_flops
from mjx_collo.planners.protocol import rollout


def load_params(
    cfg: config.Config, fixture: Path, obs_dim: int = 17, action_dim: int = 6
) -> tuple[dict, dict]:
    """World-model params shaped like ``wm_lib.init(cfg.wm)`` and the replay slice of a fixture
    written by ``benchmarks/dump_model.py`` (default sizes: cheetah's)."""
    data = np.load(fixture)
    abstract = jax.eval_shape(
        lambda: wm_lib.init(cfg.wm, jax.random.PRNGKey(0), (obs_dim,), action_dim)
    )
    leaves, treedef = jax.tree_util.tree_flatten_with_path(abstract)
    arrays = []
    for path, leaf in leaves:
        name = "wm" + jax.tree_util.keystr(path)
        if name not in data:
            raise ValueError(f"fixture {fixture} has no {name}: it was made with other wm sizes")
        arrays.append(jnp.asarray(data[name]).reshape(leaf.shape))
    replay = {k[len("replay/") :]: data[k][:, 0] for k in data.files if k.startswith("replay/")}
    return jax.tree_util.tree_unflatten(treedef, arrays), replay


def posteriors(cfg: config.Config, params, replay: dict):
    """Posterior state of every replay row, filtered along the replay slice (leading axis: rows)."""
    rows = len(replay["obs"])

    def filt(state, x):
        o, a, f, k = x
        post, _ = wm_lib.obs_step(cfg.wm, params, state, a[None], o[None], f[None], k)
        return post, post

    xs = tuple(jnp.asarray(replay[k]) for k in ("obs", "action", "is_first"))
    keys = jax.random.split(jax.random.PRNGKey(3), rows)
    _, posts = jax.jit(
        lambda: jax.lax.scan(filt, wm_lib.initial_state(cfg.wm, (1,)), xs + (keys,))
    )()
    return jax.tree.map(lambda x: x[:, 0], posts)


def contexts(cfg: config.Config, params, replay: dict, n: int = 16):
    """Posterior states at ``n`` rows spread over the later part of the replay slice."""
    rows = len(replay["obs"])
    idx = np.linspace(rows // 3, rows - 1, n).astype(int)
    return jax.tree.map(lambda x: x[idx], posteriors(cfg, params, replay))


def measure(cfg: config.Config, params, ctxs, action_dim: int = 6) -> dict:
    """Cold planning calls of ``cfg``'s planner from each context (vmapped): the mean *shadow
    return* (model reward of the plan's clipped actions rolled out through the model, so a plan
    that violates the dynamics cannot inflate it), the same for the planner's initial actions,
    the plan's own return and dynamics violation, compile time, ms per call per context, and
    matmul GFLOP per call."""
    agent = agent_lib.make_agent(cfg, action_dim)
    planner, model = agent.planner, agent.model
    pp = wm_lib.plan_params(params, None)

    def shadow(actions, ctx):
        zs = rollout(model, pp, ctx, jnp.clip(actions, -1.0, 1.0))
        return jnp.sum(jax.vmap(model.reward, in_axes=(None, 0))(pp, zs))

    def one(ctx, key):
        k1, k2 = jax.random.split(key)
        start = planner.init(pp, ctx, k1)
        plan, m, _ = planner.optimize(pp, ctx, start, k2)
        return shadow(planner.actions(plan), ctx), shadow(planner.actions(start), ctx), m

    keys = jax.random.split(jax.random.PRNGKey(5), jax.tree.leaves(ctxs)[0].shape[0])

    def call(ctx, key):  # the planning call alone, for its FLOPs
        k1, k2 = jax.random.split(key)
        return planner.optimize(pp, ctx, planner.init(pp, ctx, k1), k2)[0]

    gflop = matmul_flops(call, jax.tree.map(lambda x: x[0], ctxs), keys[0]).gflops
    t = time.perf_counter()
    fn = jax.jit(jax.vmap(one)).lower(ctxs, keys).compile()
    compile_s = time.perf_counter() - t
    jax.block_until_ready(fn(ctxs, keys))
    t = time.perf_counter()
    sh, sh0, m = jax.block_until_ready(fn(ctxs, keys))
    ms = (time.perf_counter() - t) * 1000 / keys.shape[0]
    return {
        "shadow_return": float(np.mean(sh)),
        "shadow_return_sem": float(np.std(sh) / np.sqrt(len(sh))),
        "initial_shadow_return": float(np.mean(sh0)),
        "plan_return": float(np.mean(m["plan_return"])),
        "dyn_viol": float(np.mean(m["dyn_viol"])),
        "compile_s": compile_s,
        "ms_per_call_per_ctx": ms,
        "gflop_per_call": gflop,  # matmul FLOPs, loops counted per iteration (mjx_collo.flops)
    }

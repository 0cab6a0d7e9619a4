"""MPC helpers: cache, exploration noise, clipping, warm start, non-finite fallback, vmapping,
compile-once, and plan_inner value learning."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjx_collo import agent as agent_lib
from mjx_collo import config
from mjx_collo import value as V
from mjx_collo.planner import (
    LatentModel,
    cache_len,
    make_planner,
    mpc_init,
    mpc_reset,
    next_action,
    plan_value_batch,
    replan,
    replan_value,
    shadow_batch,
)

# Integrator with reward pushing past the action bound: plans saturate beyond +1.
MODEL = LatentModel(
    start=lambda p, c, a: c + 0.1 * a,
    step=lambda p, z, a: z + 0.1 * a,
    reward=lambda p, z: jnp.sum(z) + p,
)


def _jit_replan(planner):
    return jax.jit(lambda p, c, s, k: replan(planner, p, c, s, k))


def _cfg(*overrides: str, method: str = "latco") -> config.Config:
    base = ["planner.horizon=6", "planner.mpc_steps=4", "planner.iters=5"]
    return config.load(method=method, overrides=base + list(overrides))


def test_replan_fills_cache_and_next_action_pops():
    cfg = _cfg()
    planner = make_planner(cfg, MODEL, 2)
    ctx = jnp.zeros(2)
    state = mpc_init(planner, 0.0, ctx, jax.random.PRNGKey(0))
    assert state.actions.shape == (cache_len(cfg), 2) == (4, 2)
    assert not bool(state.has_plan)
    state, m = _jit_replan(planner)(0.0, ctx, state, jax.random.PRNGKey(1))
    assert bool(state.has_plan) and int(state.pos) == 0
    assert float(m["nonfinite"]) == 0.0
    assert np.all(np.abs(state.actions) <= 1.0)
    for t in range(4):
        a, state = next_action(cfg, state, jax.random.PRNGKey(t), training=False)
        np.testing.assert_array_equal(a, state.actions[t])  # no noise at evaluation
    assert int(state.pos) == 4


def test_exploration_noise_only_in_training_and_clipped():
    cfg = _cfg("explore.noise=0.3")
    planner = make_planner(cfg, MODEL, 2)
    state = mpc_init(planner, 0.0, jnp.zeros(2), jax.random.PRNGKey(0))
    state = state.replace(actions=jnp.array([[0.0, 0.95]] * 4), has_plan=jnp.array(True), pos=0)
    keys = jax.random.split(jax.random.PRNGKey(1), 500)
    acts, _ = jax.vmap(lambda k: next_action(cfg, state, k, training=True))(keys)
    assert np.all(np.abs(acts) <= 1.0)
    assert float(jnp.std(acts[:, 0])) == pytest.approx(0.3, rel=0.15)
    assert float(jnp.max(acts[:, 1])) == 1.0  # clipped, not wrapped
    ev, _ = next_action(cfg, state, keys[0], training=False)
    np.testing.assert_array_equal(ev, state.actions[0])


def _lag1(x: np.ndarray) -> float:
    """Mean lag-1 autocorrelation along axis 1 of ``x [N, T, A]``."""
    x = x - x.mean(axis=1, keepdims=True)
    return float(np.mean(np.sum(x[:, 1:] * x[:, :-1], 1) / np.sum(x * x, 1)))


def test_colored_exploration_noise_holds_pushes_and_is_redrawn_each_episode():
    """explore.color > 0: each env's training noise is one sequence per episode, correlated over
    its steps at the same per-step scale as white noise; a reset draws a new one; the planner's
    actions carry it in training only. color 0 keeps no state (white noise per step)."""
    white = _cfg("explore.noise=0.3")
    pink = _cfg("explore.noise=0.3", "explore.color=1", "env.episode_env_steps=400")
    planner = make_planner(pink, MODEL, 2)
    mpc = mpc_init(planner, 0.0, jnp.zeros(2), jax.random.PRNGKey(0))
    mpc = mpc.replace(actions=jnp.zeros((4, 2)), has_plan=jnp.array(True), pos=jnp.int32(0))
    mpc = jax.tree.map(lambda x: jnp.broadcast_to(x, (64,) + jnp.shape(x)), mpc)
    carry0 = agent_lib.AgentCarry(post=jnp.zeros((64, 3)), prev_action=jnp.zeros((64, 2)), mpc=mpc)

    agent_w = agent_lib.Agent(white, 2, MODEL, planner)
    assert agent_lib.carry_noise(agent_lib.reset_carry(agent_w, carry0)) is None  # white: no state

    agent = agent_lib.Agent(pink, 2, MODEL, planner)
    noise = agent_lib.episode_noise(pink, 64, 2, jax.random.PRNGKey(1))
    steps = pink.env.episode_env_steps // pink.env.action_repeat
    assert noise.shape == (64, steps, 2)
    assert float(jnp.std(noise)) == pytest.approx(1.0, rel=0.1)
    assert _lag1(np.asarray(noise)) > 0.5  # pink: neighbouring steps push the same way
    white_seq = jax.random.normal(jax.random.PRNGKey(1), noise.shape)
    assert abs(_lag1(np.asarray(white_seq))) < 0.05

    carry = agent_lib.ColoredCarry(carry0.post, carry0.prev_action, carry0.mpc, noise)
    a, _ = agent_lib.act(agent, None, carry, jax.random.PRNGKey(2), True, jnp.int32(7))
    np.testing.assert_allclose(a, jnp.clip(0.3 * noise[:, 7], -1, 1), atol=1e-6)
    a_eval, _ = agent_lib.act(agent, None, carry, jax.random.PRNGKey(2), False, jnp.int32(7))
    np.testing.assert_array_equal(a_eval, 0.0)  # evaluation: the plan alone

    fresh = agent_lib.carry_noise(agent_lib.reset_carry(agent, carry, jax.random.PRNGKey(3)))
    assert fresh.shape == noise.shape and not np.allclose(fresh, noise)


def test_nonfinite_plan_falls_back_to_cache_tail_then_zeros():
    """A NaN reward makes MPPI's weights NaN. (The collocation solvers already reject non-finite
    steps, so their plans stay finite; the fallback is the last line of defence.)"""
    cfg = _cfg("planner.shooting.samples=16", "planner.shooting.elites=4", method="mppi")
    planner = make_planner(cfg, MODEL, 2)
    ctx = jnp.zeros(2)
    rp = _jit_replan(planner)
    state = mpc_init(planner, 0.0, ctx, jax.random.PRNGKey(0))
    state, _ = rp(0.0, ctx, state, jax.random.PRNGKey(1))
    _, state = next_action(cfg, state, jax.random.PRNGKey(2), training=False)
    cache = state.actions
    bad, m = rp(jnp.nan, ctx, state, jax.random.PRNGKey(3))
    assert float(m["nonfinite"]) == 1.0
    np.testing.assert_array_equal(bad.actions[:3], cache[1:])
    np.testing.assert_array_equal(bad.actions[3], 0.0)
    assert not bool(bad.has_plan) and int(bad.pos) == 0
    worse, _ = rp(jnp.nan, ctx, bad, jax.random.PRNGKey(4))
    np.testing.assert_array_equal(worse.actions, 0.0)  # no previous plan: zeros
    reset = mpc_reset(state)
    assert not bool(reset.has_plan) and int(reset.pos) == cache_len(cfg)


@pytest.mark.parametrize("method", ["latco", "mppi_value"])
def test_warm_start_shifts_previous_plan(method):
    """With zero iterations the plan returned is the start plan: the shifted previous one."""
    extra = ["planner.shooting.warm_start=true"] if method == "mppi_value" else []
    model = MODEL._replace(value=lambda p, z: jnp.sum(z))
    warm = _cfg("planner.warm_start=true", *extra, method=method)
    planner = make_planner(warm, model, 2)
    ctx = jnp.zeros(2)
    state = mpc_init(planner, 0.0, ctx, jax.random.PRNGKey(0))
    state, _ = _jit_replan(planner)(0.0, ctx, state, jax.random.PRNGKey(1))
    prev = planner.actions(state.plan)
    zero_iters = _cfg(
        "planner.warm_start=true",
        "planner.iters=0",
        "planner.shooting.iters=0",
        *extra,
        method=method,
    )
    planner0 = make_planner(zero_iters, model, 2)
    state2, _ = _jit_replan(planner0)(0.0, ctx, state, jax.random.PRNGKey(2))
    np.testing.assert_allclose(planner0.actions(state2.plan)[:2], prev[4:])


def test_vmapped_replan_compiles_once():
    cfg = _cfg()
    planner = make_planner(cfg, MODEL, 2)
    traces = []

    def step(params, ctx, state, key):
        traces.append(1)
        state, m = replan(planner, params, ctx, state, key)
        a, state = next_action(cfg, state, key, training=True)
        return a, state, m

    batched = jax.jit(jax.vmap(step, in_axes=(None, 0, 0, 0)))
    envs = 3
    ctx = jnp.zeros((envs, 2))
    keys = jax.random.split(jax.random.PRNGKey(0), envs)
    state = jax.vmap(lambda c, k: mpc_init(planner, 0.0, c, k))(ctx, keys)
    for i in range(3):
        a, state, m = batched(jnp.float32(i), ctx, state, keys)
    assert len(traces) == 1
    assert a.shape == (envs, 2) and m["dyn_viol"].shape == (envs,)


def test_shadow_batch_is_a_feasible_rollout():
    model = MODEL._replace(
        feat=lambda p, z: jnp.concatenate([z, z**2]),
        ctx_feat=lambda p, c: jnp.concatenate([-c, c**2]),
    )
    acts = jnp.array([[2.0, 0.0], [0.5, -0.5], [1.0, 1.0]])
    b = shadow_batch(model, 0.0, jnp.ones(2), acts)
    assert b["feat"].shape == (1, 4, 4) and b["reward"].shape == (1, 4)
    z1 = jnp.ones(2) + 0.1 * jnp.array([1.0, 0.0])  # actions clipped to [-1, 1]
    np.testing.assert_allclose(b["feat"][0, 0, :2], -1.0)
    np.testing.assert_allclose(b["feat"][0, 1, :2], z1, rtol=1e-6)
    np.testing.assert_allclose(b["reward"][0, 1], jnp.sum(z1), rtol=1e-6)
    # plan_final: one sequence per env.
    envs = plan_value_batch(
        model, 0.0, jnp.stack([jnp.ones(2), -jnp.ones(2)]), jnp.stack([acts] * 2)
    )
    assert envs["feat"].shape == (2, 4, 4) and envs["is_first"].shape == (2, 4)
    np.testing.assert_allclose(envs["feat"][0], b["feat"][0])


def test_plan_inner_value_learning_shares_updates_across_envs():
    cfg = _cfg(
        "value.layers=1",
        "value.units=8",
        "value.v_every=2",
        "value.mode=plan_inner",
        "planner.init=cem",  # the toy model has no policy prior
        method="collodreamer",
    )
    vcfg = cfg.value
    # The integrator with a value network on features of z; params are (model, value params) as
    # for the world model's adapter (world_model.latent_model).
    feat = lambda pp, z: jnp.concatenate([z, jnp.abs(z)])
    model = LatentModel(
        start=lambda pp, c, a: MODEL.start(pp[0], c, a),
        step=lambda pp, z, a: MODEL.step(pp[0], z, a),
        reward=lambda pp, z: MODEL.reward(pp[0], z),
        value=lambda pp, z: V.apply_value(vcfg, pp[1], feat(pp, z)),
        feat=feat,
    )
    planner = make_planner(cfg, model, 2)
    vstate = V.init_value(vcfg, jax.random.PRNGKey(0), 4)
    params = (jnp.float32(0.0), vstate.target)
    envs = 3
    ctx = jax.random.normal(jax.random.PRNGKey(1), (envs, 2))
    keys = jax.random.split(jax.random.PRNGKey(2), envs)
    state = jax.vmap(lambda c, k: mpc_init(planner, params, c, k))(ctx, keys)

    def one(c, s, k, vs):
        return replan_value(planner, model, params, c, s, vs, k, axis_name="envs")

    new, m, vs = jax.jit(jax.vmap(one, in_axes=(0, 0, 0, None), axis_name="envs"))(
        ctx, state, keys, vstate
    )
    leaves = jax.tree.leaves(vs.params)
    for leaf in leaves:  # identical across envs (pmean of the gradients)
        np.testing.assert_allclose(leaf, np.broadcast_to(leaf[0], leaf.shape), rtol=1e-5, atol=1e-6)
    assert int(vs.updates[0]) == cfg.planner.iters // vcfg.v_every
    first = jax.tree.leaves(vstate.params)[0]
    assert not np.allclose(leaves[0][0], first)
    # Two inner steps do not reach the hard target copy (every 100): the target is unchanged.
    for a, b in zip(jax.tree.leaves(vs.target), jax.tree.leaves(vstate.target), strict=True):
        np.testing.assert_allclose(a[0], b)
    assert np.all(np.isfinite(m["value/plan_loss"]))

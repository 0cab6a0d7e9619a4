"""Dreamer actor-critic: distribution, imagination, and improvement on a probe model."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjx_collo import actor as A
from mjx_collo import config
from mjx_collo import value as V

TARGET = jnp.array([0.6, -0.4])

# Noisy 2-D integrator; the reward pulls the state to TARGET.
PROBE = A.ImaginationModel(
    img_step=lambda p, s, a, k: s + 0.2 * a + 0.01 * jax.random.normal(k, s.shape),
    get_feat=lambda s: s,
    reward=lambda p, f: -jnp.sum(jnp.square(f - TARGET), axis=-1),
)


def _cfg(*overrides: str) -> config.Config:
    return config.load(
        method="dreamer",
        overrides=[
            "actor.layers=2",
            "actor.units=32",
            "actor.horizon=8",
            "actor.optim.lr=1e-3",
            "value.layers=2",
            "value.units=32",
            "value.optim.lr=1e-3",
            "value.target.every=1",
            *overrides,
        ],
    )


def test_tanh_normal_sample_logprob_matches_change_of_variables():
    mean, std = jnp.array([0.3, -1.0]), jnp.array([0.5, 2.0])
    a, logp = A.sample(mean, std, jax.random.PRNGKey(0))
    u = jnp.arctanh(a)
    ref = jnp.sum(jax.scipy.stats.norm.logpdf(u, mean, std) - jnp.log(1 - jnp.square(a)), axis=-1)
    np.testing.assert_allclose(logp, ref, rtol=1e-4)
    assert np.all(np.abs(a) < 1.0)


def _init_actor(cfg, seed, feat_dim, action_dim):
    return jax.jit(lambda k: A.init_actor(cfg.actor, k, feat_dim, action_dim))(
        jax.random.PRNGKey(seed)
    )


def test_act_samples_in_training_and_takes_mode_at_eval():
    cfg = _cfg()
    st = _init_actor(cfg, 0, 2, 3)
    f = jnp.ones(2)

    @jax.jit
    def run(params, key):
        mean, std = A.dist_params(cfg.actor, params, f, 3)
        ev = A.act(cfg.actor, params, f, key, training=False)
        tr = A.act(cfg.actor, params, f, key, training=True)
        return mean, std, ev, tr

    mean, std, ev, tr = run(st.params, jax.random.PRNGKey(1))
    np.testing.assert_allclose(ev, jnp.tanh(mean), rtol=1e-6)
    assert tr.shape == (3,) and not np.allclose(tr, ev)
    # D1 initial std: softplus(0 + softplus^-1(5)) + 1e-4 = 5 at a zero pre-activation.
    assert float(jnp.mean(std)) == pytest.approx(5.0, rel=0.3)


def test_actor_improves_imagined_return_on_probe():
    cfg = _cfg()
    key = jax.random.PRNGKey(0)
    ka, kv, ks = jax.random.split(key, 3)
    astate = jax.jit(lambda k: A.init_actor(cfg.actor, k, 2, 2))(ka)
    vstate = jax.jit(lambda k: V.init_value(cfg.value, k, 2))(kv)
    starts = jax.random.uniform(ks, (64, 2), minval=-1.0, maxval=1.0)

    @jax.jit
    def imagine(params):
        return A.imagine(cfg, PROBE, None, params, starts, jax.random.PRNGKey(9))

    def imagined_reward(params):
        return jnp.mean(PROBE.reward(None, imagine(params)[0][1:]))

    feats, acts, logps = imagine(astate.params)
    assert feats.shape == (9, 64, 2) and acts.shape == (8, 64, 2) and logps.shape == (8, 64)
    np.testing.assert_allclose(feats[0], starts)  # f_0 is the start state
    before = imagined_reward(astate.params)

    def body(carry, k):
        a, v = carry
        a, v, m = A.train_step(cfg, PROBE, None, a, v, starts, k)
        return (a, v), m

    (astate, vstate), metrics = jax.jit(lambda c, ks: jax.lax.scan(body, c, ks))(
        (astate, vstate), jax.random.split(jax.random.PRNGKey(1), 150)
    )
    after = imagined_reward(astate.params)
    assert np.all(np.asarray(metrics["actor/nonfinite"]) == 0.0)
    assert float(after) > float(before) + 0.1, (before, after)
    # The actor learns only through the dynamics (no REINFORCE term, entropy 0); the critic
    # tracks the improving lambda-returns.
    assert float(metrics["value/loss"][-1]) < float(metrics["value/loss"][0])


def test_flatten_starts():
    tree = {"deter": jnp.zeros((4, 5, 3)), "stoch": jnp.zeros((4, 5, 2))}
    flat = A.flatten_starts(tree, 2)
    assert flat["deter"].shape == (20, 3) and flat["stoch"].shape == (20, 2)

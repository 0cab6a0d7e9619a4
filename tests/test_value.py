"""Value learning: lambda-returns, episode masking, target schedule, constant-reward probe."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjx_collo import config
from mjx_collo import value as V


def _vcfg(*overrides: str) -> config.ValueConfig:
    return config.load(overrides=list(overrides)).value


def _init(cfg: config.ValueConfig, seed: int, feat_dim: int) -> V.ValueState:
    return jax.jit(lambda k: V.init_value(cfg, k, feat_dim))(jax.random.PRNGKey(seed))


def _train(cfg: config.ValueConfig, state: V.ValueState, batch: dict, seed: int):
    return jax.jit(lambda s, b, k: V.train_step(cfg, s, b, k))(
        state, batch, jax.random.PRNGKey(seed)
    )


def test_lambda_returns_hand_computed():
    r = jnp.array([1.0, 2.0, 3.0])
    v = jnp.array([10.0, 20.0, 30.0])
    y = V.lambda_returns(r, v, jnp.ones(3), 0.9, 0.5)
    # y2 = 3 + .9*30 = 30; y1 = 2 + .9*(.5*20 + .5*30) = 24.5; y0 = 1 + .9*(.5*10 + .5*24.5)
    np.testing.assert_allclose(y, [16.525, 24.5, 30.0], rtol=1e-6)
    # cont_0 = 0: y0 bootstraps on V(f_1) alone.
    y = V.lambda_returns(r, v, jnp.array([0.0, 1.0, 1.0]), 0.9, 0.5)
    np.testing.assert_allclose(y[0], 1 + 0.9 * 10.0, rtol=1e-6)
    # lam = 0 is TD(0); lam = 1 is the discounted sum bootstrapped at the end.
    np.testing.assert_allclose(V.lambda_returns(r, v, jnp.ones(3), 0.9, 0.0), r + 0.9 * v)
    mc = 1 + 0.9 * 2 + 0.81 * 3 + 0.729 * 30
    np.testing.assert_allclose(V.lambda_returns(r, v, jnp.ones(3), 0.9, 1.0)[0], mc, rtol=1e-6)


def test_batch_targets_do_not_cross_episode_starts():
    cfg = _vcfg("value.layers=1", "value.units=8", "value.gamma=0.9", "value.lam=0.5")
    state = _init(cfg, 0, 4)
    feat = jax.random.normal(jax.random.PRNGKey(1), (1, 5, 4))
    reward = jnp.array([[9.0, 1.0, 2.0, 3.0, 4.0]])
    is_first = jnp.array([[True, False, False, True, False]])
    y, mask = jax.jit(lambda t, b: V.batch_targets(cfg, t, b))(
        state.target, {"feat": feat, "reward": reward, "is_first": is_first}
    )
    vt = V.apply_value(cfg, state.target, feat[0])
    np.testing.assert_allclose(mask[0], [1.0, 1.0, 0.0, 1.0])
    # t=1 ends its episode's data (t+1=2 is the last state before a reset): bootstrap on V'(f_2).
    np.testing.assert_allclose(y[0, 1], 2.0 + 0.9 * vt[2], rtol=1e-5)
    np.testing.assert_allclose(y[0, 0], 1.0 + 0.9 * (0.5 * vt[1] + 0.5 * y[0, 1]), rtol=1e-5)
    # t=3 -> 4 is inside the new episode, bootstrapped at the end of the window.
    np.testing.assert_allclose(y[0, 3], 4.0 + 0.9 * vt[4], rtol=1e-5)


def test_target_clipping():
    cfg = _vcfg("value.clip=true", "value.clip_range=[0.0, 5.0]", "value.layers=1", "value.units=8")
    state = _init(cfg, 0, 3)
    batch = {
        "feat": jnp.zeros((1, 3, 3)),
        "reward": jnp.array([[0.0, 100.0, -100.0]]),
        "is_first": jnp.zeros((1, 3), bool),
    }
    y, _ = jax.jit(lambda t, b: V.batch_targets(cfg, t, b))(state.target, batch)
    assert float(jnp.max(y)) <= 5.0 and float(jnp.min(y)) >= 0.0


@pytest.mark.parametrize("kind", ["hard", "ema"])
def test_target_update_schedule(kind):
    cfg = _vcfg(
        "value.layers=1",
        "value.units=8",
        f"value.target.kind={kind}",
        "value.target.every=3",
        "value.target.tau=0.25",
        "value.optim.lr=1e-2",
    )
    state = _init(cfg, 0, 4)
    feat = jax.random.normal(jax.random.PRNGKey(1), (2, 3, 4))
    w = jnp.ones((2, 3))
    step = jax.jit(lambda s, k: V.update(cfg, s, feat, jnp.full((2, 3), 5.0), w, k))
    leaf = lambda vars_: jax.tree.leaves(vars_["params"])[0]
    for n in range(1, 7):
        prev = state
        state, m = step(state, jax.random.PRNGKey(n))
        assert int(state.updates) == n
        assert float(m["value/nonfinite"]) == 0.0
        if kind == "hard":
            expect = leaf(state.params) if n % 3 == 0 else leaf(prev.target)
        else:
            expect = 0.75 * leaf(prev.target) + 0.25 * leaf(state.params)
        np.testing.assert_allclose(leaf(state.target), expect, rtol=1e-6, atol=1e-7)
    assert not np.allclose(leaf(state.params), leaf(_init(cfg, 0, 4).params))


def test_nonfinite_update_is_skipped():
    cfg = _vcfg("value.layers=1", "value.units=8")
    state = _init(cfg, 0, 4)
    batch = {
        "feat": jnp.ones((1, 4, 4)),
        "reward": jnp.array([[0.0, jnp.nan, 1.0, 1.0]]),
        "is_first": jnp.zeros((1, 4), bool),
    }
    new, m = _train(cfg, state, batch, 1)
    assert float(m["value/nonfinite"]) == 1.0
    assert int(new.updates) == 0
    for a, b in zip(jax.tree.leaves(new), jax.tree.leaves(state), strict=True):
        np.testing.assert_array_equal(a, b)


def test_constant_reward_probe_converges_to_r_over_one_minus_gamma():
    """Reward 1 on every step of a 4-state cycle, gamma 0.9: V = sum_{j>=1} 0.9^(j-1) = 10 at every
    state (each state also appears inside the windows, so no value is left unconstrained)."""
    cfg = _vcfg(
        "value.layers=2",
        "value.units=64",
        "value.gamma=0.9",
        "value.lam=0.95",
        "value.optim.lr=3e-3",
        "value.target.kind=hard",
        "value.target.every=10",
    )
    states = jax.random.normal(jax.random.PRNGKey(0), (4, 6))
    feats = states[(jnp.arange(8)[:, None] + jnp.arange(10)[None]) % 4]
    batch = {"feat": feats, "reward": jnp.ones((8, 10)), "is_first": jnp.zeros((8, 10), bool)}
    state = _init(cfg, 1, 6)

    def body(s, k):
        return V.train_step(cfg, s, batch, k)

    state, metrics = jax.jit(lambda s, ks: jax.lax.scan(body, s, ks))(
        state, jax.random.split(jax.random.PRNGKey(2), 300)
    )
    np.testing.assert_allclose(V.apply_value(cfg, state.params, states), 10.0, atol=0.05)
    assert float(metrics["value/loss"][-1]) < 1e-3


def test_regularisers_deterministic_outside_training():
    """Batch norm + dropout (the paper's Fig. 13 setting): active in the update, deterministic in
    the planner's and the targets' evaluations."""
    norm = "batch"
    cfg = _vcfg("value.layers=2", "value.units=16", f"value.norm={norm}", "value.dropout=0.5")
    state = _init(cfg, 0, 5)
    f = jax.random.normal(jax.random.PRNGKey(1), (4, 6, 5))
    batch = {"feat": f, "reward": jnp.ones((4, 6)), "is_first": jnp.zeros((4, 6), bool)}

    @jax.jit
    def run(state, key):
        new, m = V.train_step(cfg, state, batch, key)
        # Unbatched feature (as the planner calls it), twice, and the same row inside a batch.
        one = V.apply_value(cfg, new.params, f[0, 0])
        again = V.apply_value(cfg, new.params, f[0, 0])
        return new, m, one, again, V.apply_value(cfg, new.params, f)[0, 0]

    new, m, one, again, batched = run(state, jax.random.PRNGKey(2))
    assert float(m["value/nonfinite"]) == 0.0
    assert one.shape == ()
    np.testing.assert_allclose(one, again)
    np.testing.assert_allclose(batched, one, rtol=1e-5)
    # Running statistics were updated by the training step.
    old = jax.tree.leaves(state.params["batch_stats"])
    upd = jax.tree.leaves(new.params["batch_stats"])
    assert any(not np.allclose(a, b) for a, b in zip(old, upd, strict=True))


def test_swept_floats_may_be_traced():
    """Float hyperparameters injected as tracers (sweeps) work: no Python branching on them."""
    base = _vcfg("value.layers=1", "value.units=8")
    state = _init(base, 0, 3)
    batch = {
        "feat": jnp.ones((1, 4, 3)),
        "reward": jnp.ones((1, 4)),
        "is_first": jnp.zeros((1, 4), bool),
    }

    @jax.jit
    def run(gamma, lr):
        cfg = config.with_values(base, {"gamma": gamma, "optim.lr": lr})
        return V.train_step(cfg, state, batch, jax.random.PRNGKey(1))[1]["value/target"]

    assert float(run(0.5, 1e-3)) != pytest.approx(float(run(0.9, 1e-3)))


def test_dropout_is_sweepable_and_draws_flax_masks():
    """``value.dropout`` is a float key, so a sweep passes it as a tracer: the value network must
    trace with it (before: TracerBoolConversionError in ``if self.dropout > 0.0``), and a literal
    rate must give exactly flax's own dropout masks (same layer names, same RNG streams)."""
    import flax.linen as nn

    from mjx_collo import nets

    x = jax.random.normal(jax.random.PRNGKey(0), (32, 8))
    net = nets.MLP(2, 16, out=1, dropout=0.25)
    params = net.init(jax.random.PRNGKey(1), x)
    rngs = {"dropout": jax.random.PRNGKey(2)}
    ours = net.apply(params, x, train=True, rngs=rngs)

    class FlaxMLP(nn.Module):  # the layer stack with flax's nn.Dropout, for reference
        @nn.compact
        def __call__(self, x):
            for _ in range(2):
                x = nn.elu(nn.Dense(16)(x))
                x = nn.Dropout(0.25, deterministic=False)(x)
            return nn.Dense(1)(x)

    np.testing.assert_array_equal(ours, FlaxMLP().apply(params, x, rngs=rngs))

    def swept(rate):
        return nets.MLP(2, 16, out=1, dropout=rate).apply(params, x, train=True, rngs=rngs)

    out = jax.jit(jax.vmap(swept))(jnp.asarray([0.0, 0.25]))
    np.testing.assert_allclose(out[1], ours, rtol=1e-6, atol=1e-6)
    no_dropout = nets.MLP(2, 16, out=1).apply(params, x, train=True, rngs=rngs)
    np.testing.assert_allclose(out[0], no_dropout, rtol=1e-6, atol=1e-6)
    deterministic = nets.MLP(2, 16, out=1, dropout=0.25).apply(params, x, train=False)
    np.testing.assert_allclose(deterministic, no_dropout, rtol=1e-6, atol=1e-6)

"""Plan2Explore's disagreement bonus (mjx_collo.explorer): the ensemble is unsure where it has no
data, the bonus enters only the reward of the exploring model, and a planner on it heads for the
unknown. Its training through the trainer rides in tests/test_methods.py (plan_final+explore)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjx_collo import config, explorer
from mjx_collo.config import ConfigError
from mjx_collo.planner import LatentModel, make_planner


def _disag_cfg(**kw) -> config.DisagConfig:
    base = {"heads": 5, "layers": 2, "units": 64, "lr": 3e-3, "scale": 1.0}
    return config.DisagConfig(**{**base, **kw})


@functools.cache  # shared by the tests that read a trained ensemble
def _trained(steps: int = 300):
    """Heads trained on inputs x in [-1, 0] x [-1, 1] to predict sin(3 x) (2 dims)."""
    cfg = _disag_cfg()
    state = explorer.init(cfg, jax.random.PRNGKey(0), 2, 2)
    key = jax.random.PRNGKey(1)

    def body(state, k):
        x = jax.random.uniform(
            k, (256, 2), minval=jnp.array([-1.0, -1.0]), maxval=jnp.array([0.0, 1.0])
        )
        return explorer.train_step(cfg, state, x, jnp.sin(3 * x), jnp.ones(256))

    state, m = jax.lax.scan(body, state, jax.random.split(key, steps))
    return cfg, state, m


def test_heads_disagree_where_they_saw_no_data():
    cfg, state, m = _trained()
    loss = np.asarray(m["explore/disag_loss"])
    assert loss[-20:].mean() < 0.1 * loss[:5].mean()
    seen = jax.random.uniform(jax.random.PRNGKey(2), (500, 2), minval=-1.0, maxval=0.0)
    unseen = seen.at[:, 0].add(3.0)  # x in [2, 3]: never in the data
    d_seen = float(explorer.disagreement(cfg, state.params, seen).mean())
    d_unseen = float(explorer.disagreement(cfg, state.params, unseen).mean())
    assert d_unseen > 5 * d_seen, (d_seen, d_unseen)
    # the running mean tracks the disagreement on the training data
    assert np.isclose(
        float(explorer.norm(state)), float(m["explore/disag"][-100:].mean()), rtol=0.5
    )


def test_running_mean_is_the_first_batch_disagreement_after_one_step():
    cfg = _disag_cfg()
    state = explorer.init(cfg, jax.random.PRNGKey(0), 3, 2)
    assert float(explorer.norm(state)) == 1.0  # before any data: the bonus is the raw disagreement
    x = jax.random.normal(jax.random.PRNGKey(1), (64, 3))
    state, m = explorer.train_step(cfg, state, x, jnp.zeros((64, 2)), jnp.ones(64))
    np.testing.assert_allclose(explorer.norm(state), m["explore/disag"], rtol=1e-6)


def test_masked_pairs_do_not_train_the_heads():
    cfg = _disag_cfg()
    state = explorer.init(cfg, jax.random.PRNGKey(0), 3, 2)
    x = jax.random.normal(jax.random.PRNGKey(1), (8, 3))
    new, _ = explorer.train_step(cfg, state, x, jnp.ones((8, 2)), jnp.zeros(8))
    for a, b in zip(jax.tree.leaves(state.params), jax.tree.leaves(new.params), strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_non_finite_batch_leaves_the_heads_as_they_were():
    cfg = _disag_cfg()
    state = explorer.init(cfg, jax.random.PRNGKey(0), 3, 2)
    x = jax.random.normal(jax.random.PRNGKey(1), (8, 3)).at[0, 0].set(jnp.nan)
    new, _ = explorer.train_step(cfg, state, x, jnp.ones((8, 2)), jnp.ones(8))
    for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(new), strict=True):
        np.testing.assert_array_equal(a, b)


# Integrator z' = z + a with no task reward: only the bonus can steer a plan.
MODEL = LatentModel(
    start=lambda p, c, a: c + a,
    step=lambda p, z, a: z + a,
    reward=lambda p, z: jnp.zeros(()),
    value=lambda p, z: jnp.zeros(()),
    feat=lambda p, z: z,
)


def test_the_bonus_is_the_only_change_and_scales_with_scale():
    cfg, state, _ = _trained()
    z = jnp.array([2.0, 0.5])
    q = (None, explorer.bonus_params(state))
    d = explorer.disagreement(cfg, state.params, z) / explorer.norm(state)
    for scale in (0.0, 2.0):
        m = explorer.exploring_model(MODEL, cfg, scale)
        np.testing.assert_allclose(m.reward(q, z), scale * d, rtol=1e-6)
        np.testing.assert_array_equal(m.step(q, z, jnp.ones(2)), MODEL.step(None, z, jnp.ones(2)))
        np.testing.assert_array_equal(m.value(q, z), MODEL.value(None, z))
    assert explorer.exploring_model(MODEL, cfg, 1.0).policy is None


def test_a_planner_on_the_exploring_model_heads_for_the_unknown():
    """The heads saw x <= 0 only: with no task reward, CEM on the exploring model plans towards
    x > 0, and on the plain model (or at scale 0) it has no reason to."""
    cfg, state, _ = _trained()
    pcfg = config.load(
        method="cem",
        overrides=[
            "planner.horizon=3",
            "planner.shooting.samples=200",
            "planner.shooting.iters=6",
            "planner.shooting.elites=20",
        ],
    )
    ctx = jnp.array([-0.5, 0.0])
    q = (None, explorer.bonus_params(state))

    def final_x(scale):
        planner = make_planner(pcfg, explorer.exploring_model(MODEL, cfg, scale), 2)

        def run(key):
            plan = planner.optimize(q, ctx, planner.init(q, ctx, key), key)[0]
            return ctx[0] + jnp.sum(planner.actions(plan)[:, 0])

        return np.asarray(jax.jit(jax.vmap(run))(jax.random.split(jax.random.PRNGKey(0), 4)))

    assert np.all(final_x(1.0) > 1.0), final_x(1.0)
    assert abs(final_x(0.0).mean()) < 1.0


@pytest.mark.parametrize(
    "overrides, words",
    [
        (["--method", "dreamer"], "planner.kind=dreamer acts from its actor"),
        (["env.obs=pixels"], "env.obs=pixels has none"),
        (["value.mode=plan_inner"], "value.mode=plan_inner"),
    ],
)
def test_unsupported_combinations_fail_with_one_line(overrides, words):
    method = overrides[1] if overrides[0] == "--method" else None
    over = [o for o in overrides if "=" in o]
    cfg = config.load(
        task="reacher_easy", method=method, overrides=["explore.disag.heads=3", *over]
    )
    with pytest.raises(ConfigError, match=words) as e:
        config.check_explore(cfg)
    assert "\n" not in str(e.value)


def test_its_weights_sweep_only_with_an_ensemble():
    off = config.load(task="reacher_easy")
    assert "explore.disag.scale" not in config.float_keys(off)
    with pytest.raises(ConfigError, match="cannot sweep 'explore.disag.scale'"):
        config.parse_sweep("explore.disag.scale=0.5,1", off)
    on = config.load(task="reacher_easy", overrides=["explore.disag.heads=3"])
    assert config.parse_sweep("explore.disag.scale=0.5,1", on) == {
        "explore.disag.scale": [0.5, 1.0]
    }

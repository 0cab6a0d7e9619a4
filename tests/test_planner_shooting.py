"""Shooting baselines (cem, mppi, mppi_value) on a small problem with a known optimum."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjx_collo import config
from mjx_collo.planner import LatentModel, make_planner
from mjx_collo.planners import shooting

# Integrator z' = z + a from z = 0 with reward -(z - 0.5)^2 (+ gamma^H V for mppi_value): the
# optimum moves to 0.5 in the first step and stays, a = [0.5, 0, 0].
MODEL = LatentModel(
    start=lambda p, c, a: c + a,
    step=lambda p, z, a: z + a,
    reward=lambda p, z: -jnp.sum(jnp.square(z - 0.5)),
    value=lambda p, z: -jnp.sum(jnp.square(z - 0.5)),
)
OPT = np.array([[0.5], [0.0], [0.0]])


@pytest.mark.parametrize("method", ["cem", "mppi", "mppi_value"])
def test_shooting_finds_optimum(method):
    cfg = config.load(
        method=method,
        overrides=[
            "planner.horizon=3",
            "planner.shooting.samples=400",
            "planner.shooting.iters=12",
            "planner.shooting.elites=40",
            "planner.shooting.min_std=0.0",
            "planner.shooting.temperature=50.0",
            "planner.shooting.init_std=1.0",
        ],
    )
    planner = make_planner(cfg, MODEL, 1)
    ctx = jnp.zeros(1)

    def run(key):
        return planner.optimize(None, ctx, planner.init(None, ctx, key), key)[:2]

    plan, m = jax.jit(jax.vmap(run))(jax.random.split(jax.random.PRNGKey(0), 4))
    np.testing.assert_allclose(plan.mean, np.broadcast_to(OPT, (4, 3, 1)), atol=0.05)
    assert np.all(m["plan_return"] > -0.01)
    assert np.all(m["dyn_viol"] == 0.0)


def test_mppi_value_bootstrap_changes_the_plan():
    """With a value favouring z = -1 beyond the horizon, mppi_value heads there, mppi does not."""
    model = MODEL._replace(value=lambda p, z: -100.0 * jnp.sum(jnp.square(z + 1.0)))
    over = [
        "planner.horizon=3",
        "planner.shooting.samples=400",
        "planner.shooting.iters=10",
        "planner.shooting.elites=40",
        "planner.gamma=0.9",
    ]
    outs = {}
    for method in ("mppi", "mppi_value"):
        cfg = config.load(method=method, overrides=over)
        planner = make_planner(cfg, model, 1)
        key = jax.random.PRNGKey(1)
        outs[method] = planner.optimize(None, jnp.zeros(1), planner.init(None, None, key), key)[0]
    assert float(jnp.sum(outs["mppi"].mean)) > 0.3
    assert float(jnp.sum(outs["mppi_value"].mean)) < -0.5


def test_shift_keeps_mean_tail_zero_and_resets_std():
    cfg = config.load(method="mppi_value", overrides=["planner.horizon=4"])
    prev = shooting.ShootState(mean=jnp.arange(8.0).reshape(4, 2), std=jnp.full((4, 2), 0.01))
    new = shooting.shift_shoot(cfg, prev, 1)
    np.testing.assert_allclose(new.mean[:3], prev.mean[1:])
    np.testing.assert_allclose(new.mean[3], 0.0)
    np.testing.assert_allclose(new.std, 2.0)  # TD-MPC2: std restarts at max_std


def test_samples_are_clipped_to_bounds():
    """A reward increasing without bound in z: the plan saturates at the action bound."""
    model = MODEL._replace(reward=lambda p, z: jnp.sum(z))
    cfg = config.load(
        method="cem",
        overrides=[
            "planner.horizon=3",
            "planner.shooting.samples=200",
            "planner.shooting.elites=20",
        ],
    )
    planner = make_planner(cfg, model, 1)
    key = jax.random.PRNGKey(2)
    plan, m, _ = planner.optimize(None, jnp.zeros(1), planner.init(None, None, key), key)
    assert float(jnp.max(jnp.abs(plan.mean))) <= 1.0
    assert float(jnp.min(plan.mean)) > 0.9


@pytest.mark.parametrize("steps", [15, 16])
def test_colored_noise_has_unit_variance_and_the_asked_correlation(steps):
    from mjx_collo.noise import colored_normal

    lag1 = {}
    for beta in (0.0, 1.0, 2.0):
        x = np.asarray(colored_normal(jax.random.PRNGKey(0), (4000, steps, 2), beta))
        assert x.shape == (4000, steps, 2)
        np.testing.assert_allclose(x.var(axis=(0, 2)), 1.0, atol=0.06)  # every step, every beta
        lag1[beta] = np.corrcoef(x[:, :-1].ravel(), x[:, 1:].ravel())[0, 1]
        # independent across samples and action dimensions
        assert abs(np.corrcoef(x[:, :, 0].ravel(), x[:, :, 1].ravel())[0, 1]) < 0.03
    assert abs(lag1[0.0]) < 0.03 and 0.4 < lag1[1.0] < lag1[2.0]


@pytest.mark.parametrize("method", ["cem", "collodreamer"])
def test_correlated_samples_find_a_long_push_that_white_samples_miss(method):
    """A sparse task shaped like a quadruped getting up: z' = z + 0.1 a pays 1 per step only past
    z = 1, which takes 10 steps of full push. 30 white samples per CEM iteration (z after 20 steps
    has std ~0.4) almost never get there; red samples (color 2, iCEM) usually do in the first
    iteration, and CEM then holds the push. The CEM method (planner.shooting.color) and
    ColloDreamer's CEM start (planner.init_cem.color; no collocation steps here) alike; half the
    samples red (color_frac 0.5) find it too."""
    model = LatentModel(
        start=lambda p, c, a: c + 0.1 * a,
        step=lambda p, z, a: z + 0.1 * a,
        reward=lambda p, z: jnp.sum((z > 1.0).astype(jnp.float32)),
        value=lambda p, z: jnp.zeros(()),
    )
    found = {}
    for color, frac in ((0.0, 1.0), (2.0, 1.0), (2.0, 0.5)):
        if method == "cem":
            over = ["shooting.samples=30", "shooting.elites=3", "shooting.iters=3"]
            over += [f"shooting.color={color}", f"shooting.color_frac={frac}"]
        else:  # the collocation planner's CEM start alone
            over = ["init=cem", "iters=0", "init_cem.samples=30", "init_cem.elites=3"]
            over += ["init_cem.iters=3", f"init_cem.color={color}", f"init_cem.color_frac={frac}"]
        cfg = config.load(
            method=method, overrides=["planner.horizon=20"] + [f"planner.{o}" for o in over]
        )
        planner = make_planner(cfg, model, 1)

        def run(key, planner=planner):
            ctx = jnp.zeros(1)
            return planner.optimize(None, ctx, planner.init(None, ctx, key), key)[1]

        m = jax.jit(jax.vmap(run))(jax.random.split(jax.random.PRNGKey(3), 16))
        found[color, frac] = int(np.sum(np.asarray(m["plan_return"]) > 0))
    assert found[0.0, 1.0] <= 4 and found[2.0, 1.0] >= 12 and found[2.0, 0.5] >= 7, found


def test_a_mixed_population_draws_a_white_block_and_a_colored_block():
    """color_frac 0.25 of 40 samples: the first 30 white (no correlation between steps), the last
    10 red (strong correlation); color_frac 1 draws exactly the all-colored noise of before."""
    from mjx_collo.noise import colored_normal
    from mjx_collo.planners.shooting import _sample_noise

    cfg = config.load(method="cem", overrides=["planner.shooting.samples=40"])
    sc = cfg.planner.shooting.model_copy(update={"color": 2.0, "color_frac": 0.25})
    key = jax.random.PRNGKey(5)
    x = np.asarray(jax.vmap(lambda k: _sample_noise(sc, k, (16, 3)))(jax.random.split(key, 200)))
    assert x.shape == (200, 40, 16, 3)

    def lag1(block):
        return np.corrcoef(block[:, :, :-1].ravel(), block[:, :, 1:].ravel())[0, 1]

    assert abs(lag1(x[:, :30])) < 0.03 and lag1(x[:, 30:]) > 0.6
    every = sc.model_copy(update={"color_frac": 1.0})
    np.testing.assert_array_equal(
        np.asarray(_sample_noise(every, key, (16, 3))),
        np.asarray(colored_normal(key, (40, 16, 3), 2.0)),
    )


def test_part_of_the_cem_start_centred_on_zero_leaves_a_poor_prior_proposal():
    """The quadruped's failure in small (docs/EXPERIMENTS.md, "Planning from the policy prior
    flips the quadruped"): staying at z = 0 (zero action) is best, the prior proposes a full push
    away. A CEM start of 30 narrow samples x 3 centred on the prior's plan cannot leave it; with
    half of the first population centred on zero (planner.init_cem.prior_frac 0.5) the elites
    find the still plan. prior_frac 1 is the CEM centred on the prior alone, as before."""
    model = LatentModel(
        start=lambda p, c, a: c + a,
        step=lambda p, z, a: z + a,
        reward=lambda p, z: -jnp.sum(jnp.square(z)),
        value=lambda p, z: -jnp.sum(jnp.square(z)),
        policy=lambda p, z: jnp.ones(1),
        ctx_policy=lambda p, c: jnp.ones(1),
    )
    first_action = {}
    for frac in (1.0, 0.5):
        over = ["init=policy_cem", "iters=0", "horizon=5", "init_cem.samples=30"]
        over += ["init_cem.elites=3", "init_cem.iters=3", "init_cem.std=0.1"]
        over += [f"init_cem.prior_frac={frac}"]
        cfg = config.load(method="collodreamer", overrides=[f"planner.{o}" for o in over])
        planner = make_planner(cfg, model, 1)

        def run(key, planner=planner):
            ctx = jnp.zeros(1)
            return planner.optimize(None, ctx, planner.init(None, ctx, key), key)[0].a[0, 0]

        first_action[frac] = np.asarray(
            jax.jit(jax.vmap(run))(jax.random.split(jax.random.PRNGKey(0), 8))
        )
    assert np.all(first_action[1.0] > 0.6), first_action  # stuck near the prior's push of 1
    assert np.all(np.abs(first_action[0.5]) < 0.3), first_action  # the still plan

"""Collocation planner: solver internals, multiplier update, and probes with known answers."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjx_collo import config
from mjx_collo.planner import LatentModel, make_planner
from mjx_collo.planners import collocation, duals, solvers
from mjx_collo.planners import objective as obj

# Linear latent model z' = F z + G a with G invertible and reward -||z - z*||^2: every reward can be
# maximal at once (z_t = z* for t >= 1), so the optimum of the constrained problem is analytic
# and the same for the exact objective and LatCo's softplus surrogate.
F = jnp.array([[0.9, 0.2], [-0.1, 0.8]])
G = jnp.array([[1.0, 0.3], [0.0, 0.7]])
Z_STAR = jnp.array([0.5, -0.3])
LQ = LatentModel(
    start=lambda p, ctx, a: F @ ctx + G @ a,
    step=lambda p, z, a: F @ z + G @ a,
    reward=lambda p, z: -jnp.sum(jnp.square(z - Z_STAR)),
)
CTX = jnp.zeros(2)
A0_STAR = jnp.linalg.solve(G, Z_STAR - F @ CTX)
AT_STAR = jnp.linalg.solve(G, Z_STAR - F @ Z_STAR)

SOLVER_SETTINGS = {
    "gauss_newton": ["planner.iters=80", "planner.dyn_eps=1e-6"],
    "cg": ["planner.iters=80", "planner.dyn_eps=1e-6"],
    "adam": ["planner.iters=1000", "planner.dyn_eps=1e-4", "planner.adam_decay=0.01"],
}


def _cfg(method: str, *overrides: str) -> config.Config:
    """Config for the probe problems. They test the solvers from a cold start (small random
    actions): the default CEM start (planner.init=cem) is tested on its own below."""
    return config.load(method=method, overrides=["planner.init=rollout", *overrides])


def _solve(cfg, model, ctx, key, params=None, action_dim=2):
    planner = make_planner(cfg, model, action_dim)

    def run(k):
        plan, metrics, _ = planner.optimize(params, ctx, planner.init(params, ctx, k), k)
        return plan, metrics

    return jax.jit(jax.vmap(run))(jax.random.split(key, 3))


@pytest.mark.parametrize("solver", ["gauss_newton", "cg", "adam"])
def test_latco_reaches_lq_optimum(solver):
    cfg = _cfg("latco", f"planner.solver={solver}", "planner.horizon=10", *SOLVER_SETTINGS[solver])
    plan, m = _solve(cfg, LQ, CTX, jax.random.PRNGKey(0))
    np.testing.assert_allclose(plan.a[:, 0], np.broadcast_to(A0_STAR, (3, 2)), atol=1e-3)
    np.testing.assert_allclose(plan.a[:, 1:], np.broadcast_to(AT_STAR, (3, 9, 2)), atol=1e-3)
    np.testing.assert_allclose(plan.z, np.broadcast_to(Z_STAR, (3, 10, 2)), atol=1e-3)
    assert np.all(m["dyn_viol_max"] < cfg.planner.dyn_eps)
    assert np.all(m["feasible"] == 1.0)
    assert np.all(m["iters_to_feasible"] < cfg.planner.iters)


@pytest.mark.parametrize("solver", ["gauss_newton", pytest.param("cg", marks=pytest.mark.slow)])
def test_latco_action_bounds_active(solver):
    """Target far away on an integrator: the optimum is a_t = +1 (bound active at every step)."""
    model = LatentModel(
        start=lambda p, c, a: c + 0.1 * a,
        step=lambda p, z, a: z + 0.1 * a,
        reward=lambda p, z: -jnp.sum(jnp.square(z - 5.0)),
    )
    cfg = _cfg(
        "latco",
        f"planner.solver={solver}",
        "planner.horizon=10",
        "planner.iters=60",
        "planner.dyn_eps=1e-5",
        "planner.act_eps=1e-6",
        "planner.cg_iters=40",
    )
    plan, m = _solve(cfg, model, jnp.zeros(1), jax.random.PRNGKey(1), action_dim=1)
    np.testing.assert_allclose(plan.a, 1.0, atol=1e-3)
    assert np.all(m["dyn_viol_max"] < 5 * cfg.planner.dyn_eps)


def test_multiplier_update_matches_latco_formula():
    lam = jnp.array([1.0, 2.0, 0.5, 3.0, 1.0])
    viol = jnp.array([0.0, 9e-3, 1e-2, 1.0, 100.0])
    eps, alpha, eta = 1e-2, 0.1, 0.1
    new = duals.update_multiplier(lam, viol, eps, alpha, eta, 1e-6, 1e12)
    # lambda + 0.1 * lambda * log10((viol + 0.1 eps) / eps), LC latco.py
    expected = [
        1.0 * (1 + 0.1 * np.log10(0.1)),  # 0.9
        2.0 * (1 + 0.1 * np.log10(1.0)),  # fixed point viol = 0.9 eps
        0.5 * (1 + 0.1 * np.log10(1.1)),
        3.0 * (1 + 0.1 * np.log10(100.1)),
        1.0 * (1 + 0.1 * np.log10(10000.1)),  # x1.4 at random initialisation
    ]
    np.testing.assert_allclose(new, expected, rtol=1e-6)
    np.testing.assert_allclose(new[jnp.array([0, 1, 4])], [0.9, 2.0, 1.4], rtol=1e-5)


def test_multiplier_stays_positive_clamped_and_nan_safe():
    update = jax.jit(lambda lam, v: duals.update_multiplier(lam, v, 1e-2, 0.1, 0.1, 1e-6, 1e12))
    lam = jnp.ones(4)
    for k in range(300):
        viol = jnp.array([0.0, 1e30, jnp.nan, jnp.inf if k % 2 else 0.0])
        lam = update(lam, viol)
        assert np.all(np.asarray(lam) > 0) and np.all(np.isfinite(np.asarray(lam)))
    np.testing.assert_allclose(lam[:3], [1e-6, 1e12, 1.0], rtol=1e-5)
    # Constants with alpha |log eta| > 1 would make the raw factor negative: the clamp keeps lam > 0.
    lam = duals.update_multiplier(jnp.ones(1), jnp.zeros(1), 1e-2, 0.9, 1e-3, 1e-6, 1e12)
    assert float(lam[0]) == pytest.approx(1e-6)


def test_kappa_normalisation():
    lam = jnp.array([4.0, 16.0])
    nu = jnp.array([1.0, 9.0])
    assert float(duals.kappa(lam, nu, 1.0, 2.0)) == pytest.approx(1.0 / (3.0 + 2.0 * 2.0 + 1.0))


def test_block_tridiag_solve_matches_dense():
    t, n = 5, 3
    rng = np.random.default_rng(0)
    blocks = np.abs(np.arange(t * n)[:, None] // n - np.arange(t * n)[None, :] // n)
    band = (blocks <= 1).astype(np.float32)
    m = rng.normal(size=(t * n, t * n)).astype(np.float32) * band
    # Symmetric, block-tridiagonal and diagonally dominant (so SPD).
    m = 0.5 * (m + m.T) + 2.0 * t * n * np.eye(t * n, dtype=np.float32)
    diag = np.stack([m[i * n : (i + 1) * n, i * n : (i + 1) * n] for i in range(t)])
    off = np.stack([m[(i + 1) * n : (i + 2) * n, i * n : (i + 1) * n] for i in range(t - 1)])
    rhs = rng.normal(size=(t, n)).astype(np.float32)
    x = jax.jit(solvers.block_tridiag_solve)(diag, off, rhs)
    np.testing.assert_allclose(x.reshape(-1), np.linalg.solve(m, rhs.reshape(-1)), rtol=1e-4)


def test_gn_and_cg_steps_equal_dense_gauss_newton():
    """One block-tridiagonal GN step and a converged CG step equal the dense damped GN step on a
    nonlinear model with action violations and the value row."""
    zdim, adim, horizon = 3, 2, 5
    k1, k2, k3, k4 = jax.random.split(jax.random.PRNGKey(1), 4)
    fm = jax.random.normal(k1, (zdim, zdim)) * 0.5
    gm = jax.random.normal(k2, (zdim, adim))
    model = LatentModel(
        start=lambda p, c, a: jnp.tanh(fm @ c + gm @ a),
        step=lambda p, z, a: jnp.tanh(fm @ z + gm @ a),
        reward=lambda p, z: -jnp.sum(jnp.square(z - 0.3)),
        value=lambda p, z: 50.0 * jnp.sum(z),
    )
    cfg = _cfg("collodreamer", f"planner.horizon={horizon}")
    prob = obj.make_problem(cfg, model, None, jnp.full((zdim,), 0.2))
    z = jax.random.normal(k3, (horizon, zdim))
    a = 1.5 * jax.random.normal(k4, (horizon, adim))
    lam = jnp.exp(jax.random.normal(k1, (horizon,)))
    nu = jnp.exp(jax.random.normal(k2, (horizon,)))
    w = obj.weights(prob, lam, nu)
    x0, unravel = jax.flatten_util.ravel_pytree((z, a))

    def res(x):
        zz, aa = unravel(x)
        return jax.flatten_util.ravel_pytree(obj.weighted(obj.raw_residuals(prob, zz, aa), w))[0]

    @jax.jit
    def steps(x):
        jac = jax.jacfwd(res)(x)
        dx = jnp.linalg.solve(1e-3 * jnp.eye(x.size) + 2 * jac.T @ jac, 2 * jac.T @ res(x))
        zz, aa = unravel(x)
        gn = solvers.gauss_newton_step(prob, zz, aa, w, 1e-3)[:2]
        cg = solvers.cg_step(prob, zz, aa, w, 1e-3, 60)[:2]
        return unravel(x - dx), gn, cg

    (z_ref, a_ref), (zg, ag), (zc, ac) = steps(x0)
    for got, ref in ((zg, z_ref), (ag, a_ref), (zc, z_ref), (ac, a_ref)):
        np.testing.assert_allclose(got, ref, atol=2e-3, rtol=2e-3)


def test_value_row_scale_auto():
    cfg = _cfg("collodreamer", "planner.horizon=30", "planner.gamma=0.99")
    model = LQ._replace(value=lambda p, z: jnp.sum(z))
    prob = obj.make_problem(cfg, model, None, CTX)
    assert float(prob.value_scale) == pytest.approx(np.sqrt(0.99**30 / 0.01), rel=1e-5)
    assert prob.bootstrap
    assert not obj.make_problem(_cfg("latco"), LQ, None, CTX).bootstrap


def test_collodreamer_needs_a_value():
    with pytest.raises(ValueError, match="needs model.value"):
        obj.make_problem(_cfg("collodreamer"), LQ, None, CTX)


def _beyond_horizon_model():
    """Integrator z' = z + 0.1 a. A small reward bump at z = 0 is all the horizon can see; a reward
    of 1 per step waits at z >= 3, which takes 30 steps. The value is that of heading right:
    V(z) = gamma^(max(3 - z, 0) / 0.1) / (1 - gamma) (excluding z's own reward)."""
    gamma = 0.99

    def reward(p, z):
        return 0.2 * jnp.exp(-jnp.sum(z**2) / 0.1) + jax.nn.sigmoid(20.0 * (jnp.sum(z) - 3.0))

    def value(p, z):
        steps = jnp.maximum(3.0 - jnp.sum(z), 0.0) / 0.1
        return gamma**steps / (1.0 - gamma)

    return LatentModel(
        start=lambda p, c, a: c + 0.1 * a,
        step=lambda p, z, a: z + 0.1 * a,
        reward=reward,
        value=value,
    )


@pytest.mark.parametrize(
    "solver,iters", [("adam", 400), pytest.param("cg", 100, marks=pytest.mark.slow)]
)
def test_value_bootstrap_reaches_beyond_horizon(solver, iters):
    model = _beyond_horizon_model()
    common = [
        "planner.horizon=10",
        f"planner.iters={iters}",
        "planner.gamma=0.99",
        f"planner.solver={solver}",
        "planner.init_std=0.1",
        "planner.value_lambda=1.0",  # the paper's end bootstrap (Eq. 10); lambda < 1: below
    ]
    ctx = jnp.zeros(1)
    plan_cd, m_cd = _solve(
        _cfg("collodreamer", *common), model, ctx, jax.random.PRNGKey(2), None, 1
    )
    plan_lc, m_lc = _solve(_cfg("latco", *common), model, ctx, jax.random.PRNGKey(2), None, 1)
    # ColloDreamer heads right (GN: at full speed); LatCo stays on the bump it can see.
    assert np.all(plan_cd.z[:, -1, 0] > 0.6)
    assert np.all(np.mean(plan_cd.a[:, :, 0], axis=1) > 0.6)
    if solver == "cg":
        assert np.all(plan_cd.a[:, :, 0] > 0.9)
    assert np.all(np.abs(plan_lc.z[:, -1, 0]) < 0.1)
    assert np.all(np.abs(plan_lc.a[:, 0, 0]) < 0.2)
    assert np.all(m_cd["plan_value"] > m_lc["plan_value"])


def test_warm_start_shifts_actions_and_rolls_states_from_the_current_context():
    cfg = _cfg("latco", "planner.horizon=6", "planner.init_lam=2.0", "planner.init_nu=3.0")
    prob = obj.make_problem(cfg, LQ, None, CTX)
    prev = collocation.init_plan(cfg, prob, jax.random.PRNGKey(0), 2)
    # A previous plan made from another context, with an out-of-bounds action and grown multipliers.
    prev = prev.replace(
        z=prev.z + 5.0, a=prev.a.at[5, 0].set(3.0), lam=prev.lam * 7.0, nu=prev.nu * 5.0
    )
    new = collocation.shift_plan(cfg, prob, prev, 4)
    np.testing.assert_allclose(new.a[:1], prev.a[4:5])
    np.testing.assert_allclose(new.a[1:], np.broadcast_to([1.0, prev.a[5, 1]], (5, 2)))  # clipped
    z = F @ CTX + G @ new.a[0]  # states rolled out from the current context, not the old plan's
    for t in range(6):
        if t:
            z = F @ z + G @ new.a[t]
        np.testing.assert_allclose(new.z[t], z, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(obj.raw_residuals(prob, new.z, new.a).d, 0.0, atol=1e-5)
    np.testing.assert_allclose(new.lam, 2.0)
    np.testing.assert_allclose(new.nu, 3.0)


def test_cold_init_is_a_feasible_rollout():
    cfg = _cfg("latco", "planner.horizon=5")
    prob = obj.make_problem(cfg, LQ, None, CTX)
    plan = collocation.init_plan(cfg, prob, jax.random.PRNGKey(0), 2)
    raw = obj.raw_residuals(prob, plan.z, plan.a)
    np.testing.assert_allclose(raw.d, 0.0, atol=1e-6)
    np.testing.assert_allclose(plan.lam, cfg.planner.init_lam)
    rnd = _cfg("latco", "planner.horizon=5", "planner.init=random")
    plan = collocation.init_plan(rnd, prob, jax.random.PRNGKey(0), 2)
    assert float(jnp.max(jnp.abs(obj.raw_residuals(prob, plan.z, plan.a).d))) > 0.1


def test_step_control_none_is_exact_latco_full_steps():
    """With step_control=none every GN step is taken; with lm, a cost-raising step is rejected."""
    cfg = _cfg(
        "latco",
        "planner.horizon=5",
        "planner.iters=1",
        "planner.step_control=none",
        "planner.solver=gauss_newton",
    )
    prob = obj.make_problem(cfg, LQ, None, CTX)
    plan = collocation.init_plan(cfg, prob, jax.random.PRNGKey(0), 2)
    w = obj.weights(prob, plan.lam, plan.nu)
    z_gn, a_gn, _ = jax.jit(
        lambda p: solvers.gauss_newton_step(prob, p.z, p.a, w, cfg.planner.gn_damping)
    )(plan)
    out = jax.jit(lambda p: collocation.optimize(cfg, prob, p)[0])(plan)
    np.testing.assert_allclose(out.z, z_gn, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(out.a, a_gn, rtol=1e-4, atol=1e-5)


def test_refinement_shoots_the_actions_to_the_bound_and_returns_a_feasible_plan():
    """Target far away on an integrator: the optimum is a_t = +1 everywhere. Refinement alone (no
    collocation iteration) must get there from the cold start, stay inside the bounds, and leave
    latents that are the rollout of its actions (no dynamics violation)."""
    model = LatentModel(
        start=lambda p, c, a: c + 0.1 * a,
        step=lambda p, z, a: z + 0.1 * a,
        reward=lambda p, z: -jnp.sum(jnp.square(z - 5.0)),
    )
    common = ["planner.horizon=10", "planner.init_std=0.3"]
    cfg = _cfg("latco", *common, "planner.iters=0", "planner.refine_iters=100")
    plan, m = _solve(cfg, model, jnp.zeros(1), jax.random.PRNGKey(1), action_dim=1)
    np.testing.assert_allclose(plan.a, 1.0, atol=1e-3)
    assert np.all(np.abs(plan.a) <= 1.0)
    np.testing.assert_allclose(m["dyn_viol_max"], 0.0, atol=1e-10)
    np.testing.assert_allclose(m["plan_return"], m["shadow_return"], rtol=1e-5)
    # Without refinement the same cold start stays where it began.
    cold, m0 = _solve(
        _cfg("latco", *common, "planner.iters=0"),
        model,
        jnp.zeros(1),
        jax.random.PRNGKey(1),
        action_dim=1,
    )
    assert np.all(m["shadow_return"] > m0["shadow_return"] + 10.0)


def test_cem_init_starts_collocation_in_the_better_basin():
    """Two reward peaks on an integrator: a small one near the start (z = 0.3) and a three-times
    higher one further away (z = -0.8) whose gradient vanishes at the start (~e^-32). Collocation from a
    small random start climbs the near peak; started from a small CEM on the same objective
    (``planner.init=cem``) it holds the far one. The CEM start is a feasible rollout in the bounds."""

    def bump(z, c):
        return jnp.exp(-jnp.sum(jnp.square(z - c)) / 0.02)

    model = LatentModel(
        start=lambda p, c, a: c + 0.3 * a,
        step=lambda p, z, a: z + 0.3 * a,
        reward=lambda p, z: bump(z, 0.3) + 3.0 * bump(z, -0.8),
    )
    common = ["planner.horizon=15", "planner.iters=100", "planner.init_std=0.05"]
    cem = _cfg("latco", *common, "planner.init=cem")
    prob = obj.make_problem(cem, model, None, jnp.zeros(1))
    start = collocation.init_plan(cem, prob, jax.random.PRNGKey(0), 1)
    np.testing.assert_allclose(obj.raw_residuals(prob, start.z, start.a).d, 0.0, atol=1e-6)
    assert np.all(np.abs(start.a) <= 1.0)

    ctx, key = jnp.zeros(1), jax.random.PRNGKey(2)
    plan, _ = _solve(cem, model, ctx, key, action_dim=1)
    near, m_near = _solve(_cfg("latco", *common), model, ctx, key, action_dim=1)
    np.testing.assert_allclose(near.z[:, -1, 0], 0.3, atol=0.1)
    np.testing.assert_allclose(plan.z[:, -1, 0], -0.8, atol=0.1)
    # The CEM start alone (no collocation iteration) already ends in the far basin and beats the
    # converged near plan in the model: the sampling stage, not the gradient stage, finds the
    # basin. Measured (3 contexts): the default 30 x 6 start ends at z = -0.80 / -1.13 / -0.64 with
    # shadow returns 27.4 / 23.9 / 15.5, 100 x 4 at -0.78 / -0.81 / -0.71 with 28.8 / 26.0 / 29.5;
    # the near plan returns 14.4-14.9.
    only_cem, m_start = _solve(
        _cfg("latco", *common, "planner.init=cem", "planner.iters=0"), model, ctx, key, action_dim=1
    )
    assert np.all(only_cem.z[:, -1, 0] < -0.4), only_cem.z[:, -1, 0]
    assert np.all(m_start["shadow_return"] > m_near["shadow_return"] + 0.5)


def test_lambda_return_matches_the_mixture_of_k_step_returns():
    """G^lam = sum_{k<H} (1-lam) lam^(k-1) R_k + lam^(H-1) R_H with the k-step returns
    R_k = sum_{j<=k} gamma^(j-1) r_j + gamma^k V(z_k); lam = 1 is the end bootstrap."""
    from mjx_collo.planners.protocol import discounted_return, lambda_return

    r = jax.random.uniform(jax.random.PRNGKey(0), (7,))
    v = 10.0 * jax.random.uniform(jax.random.PRNGKey(1), (7,))
    gamma, h = 0.9, 7
    disc = gamma ** np.arange(h)
    r_k = [float(np.sum(disc[:k] * r[:k]) + gamma**k * v[k - 1]) for k in range(1, h + 1)]
    for lam in (0.0, 0.5, 0.95):
        mix = (
            sum((1 - lam) * lam ** (k - 1) * r_k[k - 1] for k in range(1, h))
            + lam ** (h - 1) * r_k[-1]
        )
        np.testing.assert_allclose(lambda_return(r, v, gamma, lam), mix, rtol=1e-5)
    np.testing.assert_allclose(
        lambda_return(r, v, gamma, 1.0), discounted_return(r, v[-1], gamma, True), rtol=1e-6
    )


def test_value_lambda_plans_through_the_values_of_every_state():
    """With value_lambda < 1 the Adam collocation still heads for the reward beyond the horizon
    (the value of the states on the way says so), and the objective it reports is the
    lambda-return of the plan, not the end bootstrap."""
    model = _beyond_horizon_model()
    common = ["planner.horizon=10", "planner.iters=400", "planner.init_std=0.1"]
    ctx = jnp.zeros(1)
    cfg = _cfg("collodreamer", *common, "planner.value_lambda=0.8")
    plan, m = _solve(cfg, model, ctx, jax.random.PRNGKey(2), None, 1)
    assert np.all(plan.z[:, -1, 0] > 0.6)
    prob = obj.make_problem(cfg, model, None, ctx)
    assert prob.lambda_values
    end_only = obj.make_problem(
        _cfg("collodreamer", *common, "planner.value_lambda=1.0"), model, None, ctx
    )
    j_lam, _, _ = obj.exact_terms(prob, plan.z[0], plan.a[0])
    j_end, _, _ = obj.exact_terms(end_only, plan.z[0], plan.a[0])
    np.testing.assert_allclose(m["plan_return"][0], j_lam, rtol=1e-5)
    assert abs(float(j_lam) - float(j_end)) > 1e-3


def test_value_lambda_needs_the_adam_solver():
    cfg = _cfg("collodreamer", "planner.solver=gauss_newton", "planner.value_lambda=0.9")
    model = _beyond_horizon_model()
    with pytest.raises(ValueError, match="value_lambda=0.9 needs planner.solver=adam"):
        obj.make_problem(cfg, model, None, jnp.zeros(1))

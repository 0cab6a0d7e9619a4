"""The policy prior (``planner.init: policy``): a probe with a known answer.

On a linear latent model ``z' = F z + G a`` with reward ``-||z - z*||^2`` (G invertible) the best
plan reaches z* in one step and stays: ``a_k = G^-1 (z* - F z_k)``, an affine function of the
state, so a policy can represent the optimum exactly. The real actor update
(``actor.actor_step``, Dreamer's objective through the model, as the trainer runs it for the
prior) learns it from imagined rollouts; a collocation plan started from that policy's rollout is
near the optimum at once and needs far fewer solver iterations than one started from noise.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from mjx_collo import actor as actor_lib
from mjx_collo import config
from mjx_collo import value as value_lib
from mjx_collo.actor import ImaginationModel
from mjx_collo.planner import LatentModel, make_planner
from mjx_collo.planners.protocol import rollout

F = jnp.array([[0.9, 0.2], [-0.1, 0.8]])
G = jnp.array([[1.0, 0.3], [0.0, 0.7]])
Z_STAR = jnp.array([0.5, -0.3])
H = 10


def reward(z):
    return -jnp.sum(jnp.square(z - Z_STAR), -1)


def optimal_action(z):
    return jnp.linalg.solve(G, (Z_STAR - z @ F.T).T).T


def _cfg(*overrides):
    return config.load(
        method="latco",
        overrides=[
            f"planner.horizon={H}",
            "planner.solver=adam",
            "planner.dyn_eps=1e-4",
            "planner.adam_decay=0.01",
            "actor.layers=1",
            "actor.units=32",
            "actor.horizon=6",
            "actor.entropy=0.0",
            "actor.init_std=0.3",
            "actor.min_std=0.01",
            "actor.optim.lr=3e-3",
            "value.layers=1",
            "value.units=8",
            "value.gamma=0.9",
            *overrides,
        ],
    )


def _learn_prior(cfg, steps=1500):
    """The actor, trained by the real actor update on imagined rollouts of the linear model from
    random starts; the value it bootstraps with is zero (a target network with zeroed weights),
    so its objective is the discounted imagined reward, whose optimum is the one above."""
    imag = ImaginationModel(
        img_step=lambda p, s, a, k: s @ F.T + a @ G.T,
        get_feat=lambda s: s,
        reward=lambda p, f: reward(f),
    )
    astate = actor_lib.init_actor(cfg.actor, jax.random.PRNGKey(0), 2, 2)
    target = jax.tree.map(
        jnp.zeros_like, value_lib.init_value(cfg.value, jax.random.PRNGKey(1), 2).target
    )

    @jax.jit
    def step(astate, key):
        ks, ka = jax.random.split(key)
        starts = 0.25 * jax.random.normal(ks, (64, 2))
        astate, _, m = actor_lib.actor_step(cfg, imag, None, astate, target, starts, ka)
        return astate, m["actor/loss"]

    for i in range(steps):
        astate, _ = step(astate, jax.random.PRNGKey(100 + i))
    return astate.params


def _model(cfg, actor_params):
    policy = lambda pp, z: actor_lib.mode(cfg.actor, pp[2], z, 2)  # noqa: E731
    return LatentModel(
        start=lambda p, ctx, a: F @ ctx + G @ a,
        step=lambda p, z, a: F @ z + G @ a,
        reward=lambda p, z: reward(z),
        policy=policy,
        ctx_policy=policy,
    )


def _plan(cfg, model, params, ctx):
    planner = make_planner(cfg, model, 2)

    @jax.jit
    def run(ctx, k):
        start = planner.init(params, ctx, k)
        plan, _, _ = planner.optimize(params, ctx, start, k)
        return start, plan

    return jax.vmap(run)(ctx, jax.random.split(jax.random.PRNGKey(7), ctx.shape[0]))


def test_the_policy_prior_learns_the_optimum_and_collocation_from_it_needs_few_iterations():
    cfg = _cfg()
    actor_params = _learn_prior(cfg)
    params = (None, None, actor_params)
    model = _model(cfg, actor_params)
    ctx = 0.15 * jax.random.normal(jax.random.PRNGKey(3), (8, 2))

    # the learned policy is the optimal affine map on the states it meets (starts, and z* on)
    # where that map stays inside the action bounds
    zs = 0.25 * jax.random.normal(jax.random.PRNGKey(4), (512, 2))
    zs = jnp.concatenate([zs, Z_STAR + 0.1 * zs])
    a_star = optimal_action(zs)
    inside = jnp.max(jnp.abs(a_star), -1) < 0.8
    assert int(inside.sum()) > 500
    learned = actor_lib.mode(cfg.actor, actor_params, zs, 2)
    err = jnp.max(jnp.abs(learned - a_star), -1)
    assert float(jnp.max(jnp.where(inside, err, 0.0))) < 0.1, float(jnp.max(err))

    def cost(plan):  # -J of the plan's actions run through the model; the optimum's is 0
        def one(c, a):
            z = rollout(model, params, c, jnp.clip(a, -1.0, 1.0))
            return -jnp.sum(reward(z))

        return float(jnp.mean(jax.vmap(one)(ctx, plan.a)))

    few = ["planner.iters=5"]
    prior_start, prior_5 = _plan(_cfg("planner.init=policy", *few), model, params, ctx)
    noise_start, noise_5 = _plan(_cfg("planner.init=rollout", *few), model, params, ctx)
    _, noise_many = _plan(_cfg("planner.init=rollout", "planner.iters=400"), model, params, ctx)
    costs = [cost(p) for p in (prior_start, prior_5, noise_start, noise_5, noise_many)]
    names = ("prior start", "prior 5 its", "noise start", "noise 5 its", "noise 400 its")
    print("cost:", ", ".join(f"{n} {c:.4f}" for n, c in zip(names, costs, strict=True)))

    assert costs[0] < 0.02 and costs[1] < 0.02  # the prior's start is (nearly) the optimum
    assert costs[2] > 50 * costs[0] and costs[3] > 50 * costs[1]  # noise: far from it
    assert costs[4] < costs[2] / 2  # collocation from noise does get closer, slowly:
    assert costs[4] > costs[1]  # 400 iterations from noise are still behind 5 from the prior


def test_behaviour_cloning_alone_learns_the_planners_actions():
    """``actor.pg=0 actor.bc=1``: the prior's update ignores the imagined returns and fits the
    actions the agent took (here the optimal ones, with exploration noise) from their features;
    with ``actor.bc=0`` the same update does not fit them."""
    imag = ImaginationModel(
        img_step=lambda p, s, a, k: s @ F.T + a @ G.T,
        get_feat=lambda s: s,
        reward=lambda p, f: 0.0 * f[..., 0],  # no reward: only the cloning term can teach
    )

    def train(cfg):
        astate = actor_lib.init_actor(cfg.actor, jax.random.PRNGKey(0), 2, 2)
        target = jax.tree.map(
            jnp.zeros_like, value_lib.init_value(cfg.value, jax.random.PRNGKey(1), 2).target
        )

        @jax.jit
        def step(astate, key):
            ks, kn, ka = jax.random.split(key, 3)
            feat = 0.25 * jax.random.normal(ks, (64, 2))
            taken = jnp.clip(optimal_action(feat) + 0.3 * jax.random.normal(kn, (64, 2)), -1, 1)
            mask = jnp.ones(64).at[:8].set(0.0)  # episode starts: no pair
            taken = taken.at[:8].set(1.0)  # what a masked pair holds must not be learned
            bc = (feat, taken, mask)
            astate, _, m = actor_lib.actor_step(cfg, imag, None, astate, target, feat, ka, bc=bc)
            return astate, m

        for i in range(800):
            astate, m = step(astate, jax.random.PRNGKey(100 + i))
        zs = 0.25 * jax.random.normal(jax.random.PRNGKey(4), (512, 2))
        a_star = optimal_action(zs)
        # away from the bounds, where clipping the noisy actions does not bias their mean
        inside = jnp.max(jnp.abs(a_star), -1) < 0.5
        err = jnp.abs(actor_lib.mode(cfg.actor, astate.params, zs, 2) - a_star)
        return float(jnp.max(jnp.where(inside[:, None], err, 0.0))), m

    err_bc, m = train(_cfg("planner.init=policy", "actor.pg=0.0", "actor.bc=1.0"))
    err_none, _ = train(_cfg("planner.init=policy", "actor.pg=0.0", "actor.bc=0.0"))
    assert float(m["actor/loss_bc"]) < 0.15  # the noise's own variance (0.09) plus clipping
    assert err_bc < 0.1, err_bc
    assert err_none > 3 * err_bc, (err_none, err_bc)

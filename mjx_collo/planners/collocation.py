"""LatCo collocation and ColloDreamer's value-bootstrapped collocation (docs/ALGORITHM.md §3, §4.1).

The plan (latents, actions, multipliers) is an explicit :class:`PlanState` carry. One planning call
runs K primal steps with the chosen solver, each followed by LatCo's multiplier update, inside one
``lax.fori_loop`` (compiled once). Multipliers start at ``init_lam``/``init_nu`` every call, so the
constraints are relaxed first and tightened as the multipliers grow.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from mjx_collo.config import Config, ShootingConfig
from mjx_collo.planners import duals, shooting, solvers
from mjx_collo.planners import objective as obj
from mjx_collo.planners.objective import Problem
from mjx_collo.planners.protocol import policy_rollout, rollout

InnerFn = Callable[[Any, "PlanState", jax.Array], Any]


@struct.dataclass
class PlanState:
    """A collocation plan. z: [H, Z] states z_1..z_H; a: [H, A] actions a_0..a_{H-1};
    lam, nu: [H] dynamics / action-bound multipliers."""

    z: jax.Array
    a: jax.Array
    lam: jax.Array
    nu: jax.Array


def reset_multipliers(cfg: Config, plan: PlanState) -> PlanState:
    """Multipliers back to ``init_lam``/``init_nu`` (every planning call, warm or cold)."""
    ones = jnp.ones_like(plan.lam)
    return plan.replace(lam=cfg.planner.init_lam * ones, nu=cfg.planner.init_nu * ones)


def init_plan(cfg: Config, prob: Problem, key: jax.Array, action_dim: int) -> PlanState:
    """Cold plan: actions ~ N(0, init_std^2) and latents rolled out under them (``planner.init:
    rollout``, feasible start), or N(0, 1) latents like LatCo (``random``), or actions chosen by a
    small CEM on the same objective J (``cem``: ``planner.init_cem``) and latents rolled out, or
    the policy prior's own rollout through the model (``policy``), or that CEM with its
    population centred on the prior's actions (``policy_cem``)."""
    pc = cfg.planner
    ka, kz = jax.random.split(key)
    if pc.init == "policy":
        z, a = policy_rollout(prob.model, prob.params, prob.ctx, pc.horizon)
        ones = jnp.ones((pc.horizon,), jnp.float32)
        return reset_multipliers(cfg, PlanState(z=z, a=a, lam=ones, nu=ones))
    if pc.init == "policy_cem":
        _, prior = policy_rollout(prob.model, prob.params, prob.ctx, pc.horizon)
        a = cem_actions(cfg, prob, ka, action_dim, mean=prior)
    elif pc.init == "cem":
        a = cem_actions(cfg, prob, ka, action_dim)
    else:
        a = pc.init_std * jax.random.normal(ka, (pc.horizon, action_dim))
    z = rollout(prob.model, prob.params, prob.ctx, a)
    if pc.init == "random":
        z = jax.random.normal(kz, z.shape, z.dtype)
    ones = jnp.ones((pc.horizon,), jnp.float32)
    return reset_multipliers(cfg, PlanState(z=z, a=a, lam=ones, nu=ones))


def cem_actions(
    cfg: Config, prob: Problem, key: jax.Array, action_dim: int, mean: jax.Array | None = None
) -> jax.Array:
    """Mean [H, A] of ``init_cem.iters`` CEM iterations (``samples`` sequences from
    N(mean, std^2), ``mean`` zero unless given, refit to the top ``elites``) scored by the
    collocation objective J of their model rollouts. With a ``mean`` (the prior's plan) and
    ``init_cem.prior_frac`` < 1, only that share of the first iteration's samples is centred on
    it and the rest on zero, so the elites can leave a poor proposal (a quadruped's still pose is
    zero action; docs/EXPERIMENTS.md, "Planning from the policy prior flips the quadruped").

    Gradient collocation from random actions finds poor local optima on a trained model; starting
    it from a cheap sampling solution gives the Lagrangian iterations a good basin to refine.
    """
    ic = cfg.planner.init_cem
    shoot = ShootingConfig.model_construct(  # no validation: std may be a swept tracer
        init_std=ic.std,
        samples=ic.samples,
        elites=ic.elites,
        iters=ic.iters,
        temperature=1.0,
        min_std=0.0,
        max_std=2.0,  # the CEM method's clamp
        warm_start=False,
        color=ic.color,
        color_frac=ic.color_frac,
    )
    sub = cfg.model_copy(
        update={"planner": cfg.planner.model_copy(update={"kind": "cem", "shooting": shoot})}
    )
    start = shooting.init_shoot(sub, action_dim)
    first = None
    if mean is not None:
        start = start.replace(mean=jnp.clip(mean, -1.0, 1.0).astype(start.mean.dtype))
        around_prior = int(round(ic.samples * ic.prior_frac))
        if around_prior < ic.samples:  # the rest of the first population around zero
            first = jnp.concatenate(
                [
                    jnp.broadcast_to(start.mean, (around_prior,) + start.mean.shape),
                    jnp.zeros((ic.samples - around_prior,) + start.mean.shape, start.mean.dtype),
                ]
            )
    state, _ = shooting.optimize_shoot(sub, prob, start, key, first_means=first)
    return jnp.clip(state.mean, -1.0, 1.0)


def shift_plan(cfg: Config, prob: Problem, prev: PlanState, shift: int) -> PlanState:
    """Warm start: drop the first ``shift`` actions of the previous plan, repeat its last action for
    the new tail, clip to the action bounds, and roll the latents out from the *current* context
    under those actions; the multipliers are reset. prev: plan of the previous call.

    The previous plan's latents are not reused: they were planned from the old context, and after
    ``shift`` real steps (exploration noise, model error) the posterior is elsewhere. Starting from
    them starts the plan off the real trajectory.
    """
    horizon = prev.a.shape[0]
    shift = min(shift, horizon)
    a_last = prev.a[-1]
    a = jnp.concatenate([prev.a[shift:], jnp.broadcast_to(a_last, (shift, a_last.shape[0]))])
    a = jnp.clip(a, -1.0, 1.0)
    z = rollout(prob.model, prob.params, prob.ctx, a)
    return reset_multipliers(cfg, prev.replace(z=z, a=a))


def _gauss_newton_primal(cfg: Config, prob: Problem, unroll: bool) -> tuple[Callable, jax.Array]:
    """GN / CG step with optional Levenberg-Marquardt step control (``planner.step_control``).

    ``none`` is exact LatCo (full steps, fixed damping). ``lm`` evaluates the GN cost of the new plan
    at the same multipliers; a step that raises it is rejected and the damping multiplied by 4,
    an accepted step divides the damping by 3 (never below ``gn_damping``). The solver state is the
    damping multiplier (a scalar, 1 at the start of every call).
    """
    pc = cfg.planner

    def solve(z, a, w, damping):
        if pc.solver == "gauss_newton":
            return solvers.gauss_newton_step(prob, z, a, w, damping)
        return solvers.cg_step(prob, z, a, w, damping, pc.cg_iters, unroll)

    def step(z, a, lam, nu, mult):
        w = obj.weights(prob, lam, nu)
        nz, na, raw = solve(z, a, w, pc.gn_damping * mult)
        if pc.step_control == "none":
            return nz, na, mult, raw.d
        old = obj.cost(raw, w)
        new = obj.cost(obj.raw_residuals(prob, nz, na), w)
        better = jnp.isfinite(new) & (new <= old)
        nz, na = jnp.where(better, nz, z), jnp.where(better, na, a)
        mult = jnp.clip(jnp.where(better, mult / 3.0, mult * 4.0), 1.0, 1e10)
        return nz, na, mult, raw.d

    return step, jnp.ones((), jnp.float32)


def _primal(cfg: Config, prob: Problem, plan: PlanState, unroll: bool) -> tuple[Callable, Any]:
    """(step_fn, initial solver state) for ``planner.solver``.

    ``step_fn(z, a, lam, nu, state) -> (z', a', state', d)`` with d: [H, Z] the dynamics residual of
    the input plan.
    """
    pc = cfg.planner
    if pc.solver in ("gauss_newton", "cg"):
        return _gauss_newton_primal(cfg, prob, unroll)
    tx = solvers.adam_optimizer(pc.adam_lr, pc.adam_decay, pc.adam_b2, pc.iters)

    def step(z, a, lam, nu, s):
        return solvers.adam_step(prob, z, a, lam, nu, s, tx)

    return step, tx.init((plan.z, plan.a))


def optimize(
    cfg: Config,
    prob: Problem,
    plan: PlanState,
    inner: tuple[int, InnerFn, Any] | None = None,
    key: jax.Array | None = None,
    unroll: bool = False,
) -> tuple[PlanState, dict[str, jax.Array], Any]:
    """Run K solver + multiplier iterations from ``plan`` (one ``fori_loop``).

    Args:
      inner: optional ``(every, fn, state)``; ``state = fn(state, plan, key)`` runs after every
        ``every``-th iteration (plan_inner value learning). Needs ``key``.
      unroll: unroll the loops (only for FLOP counting: XLA counts a loop body once).
    Returns:
      (plan, metrics, inner_state).
    """
    pc = cfg.planner
    step, solver_state = _primal(cfg, prob, plan, unroll)
    every, inner_fn, inner_state = inner if inner is not None else (0, None, ())
    if key is None:
        key = jnp.zeros((2,), jnp.uint32)
    lo, hi = pc.lam_clip

    def body(k, carry):
        p, s, last_bad, istate = carry
        z, a, s, d = step(p.z, p.a, p.lam, p.nu, s)
        dv = duals.dyn_violation(d)
        av = duals.act_violation(p.a)
        lam = duals.update_multiplier(p.lam, dv, pc.dyn_eps, pc.lm_alpha, pc.lm_eta, lo, hi)
        nu = duals.update_multiplier(p.nu, av, pc.act_eps, pc.lm_alpha, pc.lm_eta, lo, hi)
        feasible = (jnp.max(dv) <= pc.dyn_eps) & (jnp.max(av) <= pc.act_eps)
        last_bad = jnp.where(feasible, last_bad, k)
        p = PlanState(z=z, a=a, lam=lam, nu=nu)
        if inner_fn is not None:
            istate = jax.lax.cond(
                (k + 1) % every == 0,
                lambda st: inner_fn(st, p, jax.random.fold_in(key, k)),
                lambda st: st,
                istate,
            )
        return p, s, last_bad, istate

    init = (plan, solver_state, jnp.asarray(-1, jnp.int32), inner_state)
    plan, _, last_bad, inner_state = jax.lax.fori_loop(0, pc.iters, body, init, unroll=unroll)
    if pc.refine_iters > 0:
        plan = refine(cfg, prob, plan, unroll)
    metrics = plan_metrics(prob, plan, pc.dyn_eps, pc.act_eps)
    # Iterations to the violation threshold: steps after which every iterate (and the final plan)
    # met it, i.e. 1 + the last infeasible iterate; 0 if all were feasible, K + 1 if the final plan
    # is not. (A rollout-initialised plan starts feasible and usually leaves feasibility first.)
    final_ok = metrics["feasible"] > 0
    steps = jnp.where(final_ok, last_bad + 1, pc.iters + 1)
    metrics["iters_to_feasible"] = steps.astype(jnp.float32)
    return plan, metrics, inner_state


def refine(cfg: Config, prob: Problem, plan: PlanState, unroll: bool = False) -> PlanState:
    """``planner.refine_iters`` Adam steps on the actions alone, maximising the objective J of
    their model rollout (shooting), each projected onto [-1, 1]; the latents become that rollout.

    The collocation plan's return is read off latents that violate the dynamics by up to
    ``dyn_eps`` per step, and its actions are only pushed toward the bounds by multipliers; this
    polishes the actions that will be executed against the feasible trajectory they produce.
    """
    pc = cfg.planner
    tx = optax.adam(pc.refine_lr, b1=0.9, b2=pc.adam_b2)

    def body(_, carry):
        a, s = carry
        g = jax.grad(lambda x: -shadow(prob, x)[0])(a)
        u, s = tx.update(g, s)
        na = jnp.clip(optax.apply_updates(a, u), -1.0, 1.0)
        ok = jnp.all(jnp.isfinite(na))
        return jnp.where(ok, na, a), s

    a0 = jnp.clip(plan.a, -1.0, 1.0)
    a, _ = jax.lax.fori_loop(0, pc.refine_iters, body, (a0, tx.init(a0)), unroll=unroll)
    return plan.replace(a=a, z=rollout(prob.model, prob.params, prob.ctx, a))


def shadow(prob: Problem, a: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``(J, rewards [H], states [H, Z])`` of the feasible model rollout of actions ``a`` [H, A],
    taken as given (the callers clip them to the bounds)."""
    j, rs, zs, _ = obj.rollout_return(prob, a)
    return j, rs, zs


def plan_metrics(
    prob: Problem, plan: PlanState, dyn_eps: Any, act_eps: Any
) -> dict[str, jax.Array]:
    """Diagnostics of a final plan (paper Figs. 2, 10, 11; LC `opt_*`), all scalars.

    ``dyn_viol``/``act_viol`` are per-step means (LC); ``shadow_return`` is the objective J of the
    feasible rollout of the clipped plan actions, i.e. what the plan actually achieves in the model.
    """
    j, rewards, raw = obj.exact_terms(prob, plan.z, plan.a)
    dv = duals.dyn_violation(raw.d)
    av = duals.act_violation(plan.a)
    shadow_j, rs, _ = shadow(prob, jnp.clip(plan.a, -1.0, 1.0))
    return {
        "dyn_viol": jnp.mean(dv),
        "dyn_viol_max": jnp.max(dv),
        "act_viol": jnp.mean(av),
        "lam_mean": jnp.mean(plan.lam),
        "lam_max": jnp.max(plan.lam),
        "nu_mean": jnp.mean(plan.nu),
        "nu_max": jnp.max(plan.nu),
        "plan_reward": jnp.mean(rewards),
        "plan_value": raw.val,
        "plan_return": j,
        "shadow_reward": jnp.mean(rs),
        "shadow_return": shadow_j,
        "feasible": ((jnp.max(dv) <= dyn_eps) & (jnp.max(av) <= act_eps)).astype(jnp.float32),
    }

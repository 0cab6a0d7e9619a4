"""Value network, slow target, lambda-returns and the value train step (docs/ALGORITHM.md §4.3-4.4).

Convention (pitfall 7): ``V(f_t)`` estimates ``E[sum_{j>=1} gamma^(j-1) r_{t+j}]`` and *excludes* the
reward of its own state; the planner bootstraps with ``gamma^H V'(z_H)``. Targets are
``y_t = r_{t+1} + gamma [(1 - lam) V'(f_{t+1}) + lam y_{t+1}]`` bootstrapped with ``V'`` at the end
of the sequence, computed with the target network ``V'`` (hard copy every ``target.every`` updates
or EMA ``target.tau``). Dropout and batch norm are active only inside value updates; the planner and
the targets use the deterministic network.

Batches (``replay`` mode and the plan modes alike) are dicts ``{feat [B, T, F], reward [B, T],
is_first [B, T]}`` where ``reward[t]`` is received on arriving in state ``t``; a target is formed for
every ``t < T-1`` whose transition ``t -> t+1`` does not cross an episode start.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from mjx_collo import nets
from mjx_collo.config import OptimConfig, ValueConfig

Variables = Any


@struct.dataclass
class ValueState:
    """Online and target value networks with optimiser state.

    params, target: flax variable dicts (``{"params": ...}`` plus ``"batch_stats"`` with batch
    norm); updates: [] int32 count of applied (finite) updates, drives the target schedule.
    """

    params: Variables
    target: Variables
    opt_state: optax.OptState
    updates: jax.Array


def make_optimizer(cfg: OptimConfig) -> optax.GradientTransformation:
    """clip_by_global_norm + Adam(eps). Built inside traced code: floats may be tracers."""
    return optax.chain(optax.clip_by_global_norm(cfg.clip), optax.adam(cfg.lr, eps=cfg.eps))


def value_net(cfg: ValueConfig) -> nets.MLP:
    """``layers`` x ``units`` ELU MLP with a scalar head (D1: 3 x 400)."""
    return nets.MLP(cfg.layers, cfg.units, out=1, act="elu", norm=cfg.norm, dropout=cfg.dropout)


def init_value(cfg: ValueConfig, key: jax.Array, feat_dim: int) -> ValueState:
    """Fresh value state; the target starts as a copy of the online network."""
    variables = value_net(cfg).init(key, jnp.zeros((1, feat_dim)))
    variables = jax.tree.map(jnp.asarray, dict(variables))
    return ValueState(
        params=variables,
        target=variables,
        opt_state=make_optimizer(cfg.optim).init(variables["params"]),
        updates=jnp.zeros((), jnp.int32),
    )


def apply_value(cfg: ValueConfig, variables: Variables, feat: jax.Array) -> jax.Array:
    """Deterministic value (no dropout, batch-norm running statistics). feat: [..., F] -> [...]."""
    return value_net(cfg).apply(variables, feat, train=False)[..., 0]


def clip_value(cfg: ValueConfig, v: jax.Array) -> jax.Array:
    """Clamp to ``clip_range`` when ``value.clip`` (planner bootstrap and targets)."""
    return jnp.clip(v, cfg.clip_range[0], cfg.clip_range[1]) if cfg.clip else v


def lambda_returns(
    rewards: jax.Array, next_values: jax.Array, cont: jax.Array, gamma: Any, lam: Any
) -> jax.Array:
    """Lambda-returns over a sequence of transitions (reverse scan).

    Args:
      rewards: [T, ...] r_{t+1}, reward of transition t -> t+1.
      next_values: [T, ...] V'(f_{t+1}).
      cont: [T, ...] 1 where y_{t+1} exists and continues the return, 0 to bootstrap with
        V'(f_{t+1}) alone; the last entry is treated as 0.
    Returns:
      y: [T, ...] with y_t = r_{t+1} + gamma [(1 - lam) V'_{t+1} + lam (cont_t y_{t+1} +
      (1 - cont_t) V'_{t+1})].
    """
    cont = cont.at[-1].set(0.0)

    def body(y_next, xs):
        r, v, c = xs
        nxt = c * y_next + (1.0 - c) * v
        y = r + gamma * ((1.0 - lam) * v + lam * nxt)
        return y, y

    _, ys = jax.lax.scan(
        body, jnp.zeros_like(rewards[-1]), (rewards, next_values, cont), reverse=True
    )
    return ys


def batch_targets(
    cfg: ValueConfig, target: Variables, batch: dict[str, jax.Array]
) -> tuple[jax.Array, jax.Array]:
    """Lambda-return targets of a sequence batch with the target net.

    Returns:
      targets: [B, T-1] for states 0..T-2 (clipped when ``value.clip``); mask: [B, T-1] float, 0
      where the transition t -> t+1 crosses an episode start.
    """
    feat = jax.lax.stop_gradient(batch["feat"])
    rewards = batch["reward"][:, 1:]
    valid = 1.0 - batch["is_first"][:, 1:].astype(jnp.float32)
    next_v = clip_value(cfg, apply_value(cfg, target, feat[:, 1:]))
    cont = jnp.concatenate([valid[:, 1:], jnp.zeros_like(valid[:, :1])], axis=1)
    y = jax.vmap(lambda r, v, c: lambda_returns(r, v, c, cfg.gamma, cfg.lam))(rewards, next_v, cont)
    return jax.lax.stop_gradient(clip_value(cfg, y)), valid


def value_loss(
    cfg: ValueConfig,
    params: Variables,
    feat: jax.Array,
    targets: jax.Array,
    weights: jax.Array,
    key: jax.Array,
) -> tuple[jax.Array, tuple[Variables, jax.Array]]:
    """Weighted Normal(mu, 1) NLL ``sum w 0.5 (V(f) - y)^2 / sum w`` in training mode.

    feat: [B, T, F]; targets, weights: [B, T]. Returns (loss, (new batch stats, values)).
    """
    net = value_net(cfg)
    if cfg.norm == "batch":
        out, mutated = net.apply(
            params, feat, train=True, rngs={"dropout": key}, mutable=["batch_stats"]
        )
        stats = mutated["batch_stats"]
    else:
        out = net.apply(params, feat, train=True, rngs={"dropout": key})
        stats = None
    v = out[..., 0]
    w_sum = jnp.maximum(jnp.sum(weights), 1e-8)
    loss = jnp.sum(weights * 0.5 * jnp.square(v - targets)) / w_sum
    return loss, (stats, v)


def _target_update(cfg: ValueConfig, target: Variables, params: Variables, n: jax.Array):
    """Hard copy every ``target.every`` updates, or EMA with rate ``target.tau``."""
    if cfg.target.kind == "hard":
        copy = (n % cfg.target.every) == 0
        return jax.tree.map(lambda p, t: jnp.where(copy, p, t), params, target)
    tau = cfg.target.tau
    return jax.tree.map(lambda p, t: (1.0 - tau) * t + tau * p, params, target)


def update(
    cfg: ValueConfig,
    state: ValueState,
    feat: jax.Array,
    targets: jax.Array,
    weights: jax.Array,
    key: jax.Array,
    axis_name: str | None = None,
) -> tuple[ValueState, dict[str, jax.Array]]:
    """One value-network step on regression targets, then the target schedule.

    feat: [B, T, F]; targets, weights: [B, T]. With ``axis_name`` (inside a vmap over envs) the
    gradients are averaged over that axis so every env applies the same update. A non-finite loss
    or gradient skips the update (state unchanged, ``value/nonfinite`` = 1).
    """
    grad_fn = jax.value_and_grad(value_loss, argnums=1, has_aux=True)
    (loss, (stats, v)), grads = grad_fn(cfg, state.params, feat, targets, weights, key)
    grads = grads["params"]
    if axis_name is not None:
        grads, loss = jax.lax.pmean((grads, loss), axis_name)
    tx = make_optimizer(cfg.optim)
    upd, opt_state = tx.update(grads, state.opt_state, state.params["params"])
    new_p = optax.apply_updates(state.params["params"], upd)
    new_p = jax.tree.map(lambda p: p * (1.0 - cfg.optim.weight_decay), new_p)
    new_vars = {**state.params, "params": new_p}
    if stats is not None:
        if axis_name is not None:
            stats = jax.lax.pmean(stats, axis_name)
        new_vars["batch_stats"] = stats
    leaves = jax.tree.leaves((loss, grads))
    finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves]))
    pick = lambda new, old: jax.tree.map(lambda n, o: jnp.where(finite, n, o), new, old)
    n = state.updates + finite.astype(jnp.int32)
    new_target = _target_update(cfg, state.target, new_vars, n)
    new_state = ValueState(
        params=pick(new_vars, state.params),
        target=pick(new_target, state.target),
        opt_state=pick(opt_state, state.opt_state),
        updates=n,
    )
    w_sum = jnp.maximum(jnp.sum(weights), 1e-8)
    metrics = {
        "value/loss": loss,
        "value/mean": jnp.sum(weights * v) / w_sum,
        "value/target": jnp.sum(weights * targets) / w_sum,
        "value/grad_norm": optax.global_norm(grads),
        "value/nonfinite": (~finite).astype(jnp.float32),
    }
    return new_state, metrics


def train_step(
    cfg: ValueConfig,
    state: ValueState,
    batch: dict[str, jax.Array],
    key: jax.Array,
    axis_name: str | None = None,
) -> tuple[ValueState, dict[str, jax.Array]]:
    """Value step on a sequence batch (``replay`` mode: posterior features and real rewards of the
    world-model batch; plan modes: shadow rollouts). batch: feat [B, T, F], reward, is_first [B, T].
    """
    targets, mask = batch_targets(cfg, state.target, batch)
    feat = jax.lax.stop_gradient(batch["feat"][:, :-1])
    return update(cfg, state, feat, targets, mask, key, axis_name)

"""Recurrent state-space model (Dreamer v1 Gaussian / DreamerV2 categorical RSSM): the state,
the networks' parameters, and the transitions — posterior filtering and prior imagination.

Notation (docs/ALGORITHM.md §1): ``h`` deterministic GRU state ``[..., D]``; ``s`` stochastic
state, flat ``[..., S]`` (gaussian: ``S = stoch``; categorical: ``S = stoch * classes`` one-hot
groups); feature ``f = [s, h]`` of size ``F = S + D``; ``e = enc(o)`` embedding ``[..., E]``.

Data convention (the LC/D1 one, shared with replay.py): row ``t`` of a sequence holds ``obs_t``,
the action ``a_{t-1}`` that led into ``obs_t``, the reward ``r_t`` received on arriving in
``obs_t``, and ``is_first_t``. The posterior at ``t`` is ``q(s_t | h_t, e_t)`` with ``h_t =
GRU(s_{t-1}, a_{t-1}, h_{t-1})``; at ``is_first`` the previous state *and* the previous action are
reset to zeros.

Why the filter is laid out as it is (CPU speed; figures in docs/BENCHMARKS.md): inside the
``lax.scan`` over time only the recurrent chain runs (input layer, GRU, posterior layers, sample);
the encoder, the embedding half of the posterior layer and the prior head are applied to all
``B*T`` rows at once outside the scan; the sampling noise for all steps is drawn in one call. The
scanned dense layers can expose their inputs and take zero "taps" on their outputs, from which
:mod:`.losses` forms their weight gradients outside the scan.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from mjx_collo import nets
from mjx_collo.config import WorldModelConfig
from mjx_collo.world_model.dists import _noise, _sample, _stats, dist_mean
from mjx_collo.world_model.heads import PIXEL_NDIM, _apply, _io_nets, _reward_net, encode

Params = dict[str, Any]


@struct.dataclass
class RSSMState:
    """One RSSM state (any leading batch/time shape ``...``).

    deter: ``[..., D]``; stoch: ``[..., S]`` sample (categorical: straight-through one-hot, flat);
    stats: gaussian ``{"mean": [..., s], "std": [..., s]}``, categorical
    ``{"logits": [..., G, K]}`` (normalised log-probabilities, unimix applied).
    """

    deter: jax.Array
    stoch: jax.Array
    stats: dict[str, jax.Array]


def stoch_size(cfg: WorldModelConfig) -> int:
    """S: flat size of the stochastic state."""
    return cfg.stoch * (cfg.classes if cfg.latent == "categorical" else 1)


def feat_size(cfg: WorldModelConfig) -> int:
    """F = S + D."""
    return stoch_size(cfg) + cfg.deter


def _stat_size(cfg: WorldModelConfig) -> int:
    return 2 * cfg.stoch if cfg.latent == "gaussian" else cfg.stoch * cfg.classes


def _rssm_nets(cfg: WorldModelConfig) -> dict[str, Any]:
    stat = _stat_size(cfg)
    return {
        "img_in": nets.Linear(cfg.hidden),
        "gru": nets.GRUCell(cfg.deter, layernorm=cfg.gru_layernorm),
        "img_out": nets.MLP(1, cfg.hidden, out=stat, act=cfg.act),
        "obs_h": nets.Linear(cfg.hidden),
        "obs_e": nets.Linear(cfg.hidden, bias=False),
        "obs_out": nets.Linear(stat),
        "reward": _reward_net(cfg),
    }


def init(
    cfg: WorldModelConfig, key: jax.Array, obs_shape: tuple[int, ...], action_dim: int
) -> Params:
    """World-model parameters for observations ``obs_shape`` (``(O,)`` or ``(64, 64, C)``)."""
    obs_shape = tuple(int(n) for n in obs_shape)
    try:
        fn = _jitted_init(cfg, obs_shape, action_dim)  # compiled once per config
    except TypeError:  # unhashable config (traced swept values): trace inline
        fn = functools.partial(_init, cfg, obs_shape, action_dim)
    return fn(key)


@functools.lru_cache(maxsize=16)
def _jitted_init(cfg: WorldModelConfig, obs_shape: tuple[int, ...], action_dim: int):
    return jax.jit(functools.partial(_init, cfg, obs_shape, action_dim))


def _init(
    cfg: WorldModelConfig, obs_shape: tuple[int, ...], action_dim: int, key: jax.Array
) -> Params:
    mods = {**_rssm_nets(cfg), **_io_nets(cfg, obs_shape)}
    s, d, h = stoch_size(cfg), cfg.deter, cfg.hidden
    enc_name = "enc_conv" if len(obs_shape) == PIXEL_NDIM else "enc_mlp"
    x = jax.ShapeDtypeStruct((1,) + obs_shape, jnp.float32)
    embed_dim = jax.eval_shape(lambda x: mods[enc_name].init_with_output(key, x)[0], x).shape[-1]
    z = lambda *shape: jax.ShapeDtypeStruct((1, *shape), jnp.float32)
    dummy = {
        "img_in": (z(s + action_dim),),
        "gru": (z(h), z(d)),
        "img_out": (z(d),),
        "obs_h": (z(d),),
        "obs_e": (z(embed_dim),),
        "obs_out": (z(h),),
        "reward": (z(s + d),),
        "enc_mlp": (z(*obs_shape),),
        "enc_conv": (z(*obs_shape),),
        "dec_mlp": (z(s + d),),
        "dec_conv": (z(s + d),),
    }

    specs = {name: (mod, dummy[name]) for name, mod in mods.items()}
    # The two-hot head keeps the default random output layer. D3 zeroes it (a fresh head predicts
    # 0), but then no reward gradient reaches the hidden layers or the latent until that layer
    # has grown: on a sparse toy reward the zeroed head still predicted the base rate after 200
    # updates, where the random one had fit it (err/reward_mse 0.50 vs 0.02).
    return nets.init_many(specs, key)


def initial_state(cfg: WorldModelConfig, batch: tuple[int, ...] = ()) -> RSSMState:
    """All-zero state ``[*batch, ...]`` (the reset state; its stats are a standard prior)."""
    if cfg.latent == "gaussian":
        stats = {"mean": jnp.zeros(batch + (cfg.stoch,)), "std": jnp.ones(batch + (cfg.stoch,))}
    else:
        shape = batch + (cfg.stoch, cfg.classes)
        stats = {"logits": jnp.full(shape, -math.log(cfg.classes), jnp.float32)}  # not weak-typed
    return RSSMState(
        deter=jnp.zeros(batch + (cfg.deter,)),
        stoch=jnp.zeros(batch + (stoch_size(cfg),)),
        stats=stats,
    )


def get_feat(state: RSSMState) -> jax.Array:
    """Dreamer feature ``f = [s, h]`` -> ``[..., F]``."""
    return jnp.concatenate([state.stoch, state.deter], -1)


# Dense layers applied inside the time scan. Their weight gradients are formed outside the scan
# (see :func:`_grads`): inside, they see stop-gradient weights plus a zero "tap" on their output.
RECURRENT = ("img_in", "gru", "obs_h", "obs_out")
Taps = dict[str, jax.Array]


def _add(x: jax.Array, taps: Taps | None, name: str) -> jax.Array:
    return x if taps is None else x + taps[name]


def _transition_io(
    cfg: WorldModelConfig,
    params: Params,
    stoch: jax.Array,
    deter: jax.Array,
    action: jax.Array,
    taps: Taps | None = None,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Deterministic part of the prior: ``h' = GRU(act(Dense([s, a])), h)`` -> ``[..., D]``,
    plus the inputs of its dense layers (``img_in: [..., S + A]``, ``gru: [..., hidden + D]``)."""
    mods = _rssm_nets(cfg)
    act = nets.ACTIVATIONS[cfg.act]
    x_in = jnp.concatenate([stoch, action], -1)
    x = act(_add(_apply(mods["img_in"], params["img_in"], x_in), taps, "img_in"))
    tap = None if taps is None else taps["gru"]
    h = _apply(mods["gru"], params["gru"], x, deter, tap)
    return h, {"img_in": x_in, "gru": jnp.concatenate([x, deter], -1)}


def _transition(
    cfg: WorldModelConfig, params: Params, stoch: jax.Array, deter: jax.Array, action: jax.Array
) -> jax.Array:
    """``h' = GRU(act(Dense([s, a])), h)`` -> ``[..., D]``."""
    return _transition_io(cfg, params, stoch, deter, action)[0]


def prior_stats(cfg: WorldModelConfig, params: Params, deter: jax.Array) -> dict[str, jax.Array]:
    """Prior ``p(s | h)`` statistics from ``deter: [..., D]`` (a function of ``h`` alone)."""
    return _stats(cfg, _apply(_rssm_nets(cfg)["img_out"], params["img_out"], deter))


def prior_mean(cfg: WorldModelConfig, params: Params, deter: jax.Array) -> jax.Array:
    """``m(h)``: prior mean (gaussian) or probabilities (categorical), flat ``[..., S]``."""
    return dist_mean(cfg, prior_stats(cfg, params, deter))


def _embed_proj(cfg: WorldModelConfig, params: Params, embed: jax.Array) -> jax.Array:
    """Embedding half of the posterior's first layer: ``[..., E] -> [..., hidden]``."""
    return _apply(_rssm_nets(cfg)["obs_e"], params["obs_e"], embed)


def _post_stats_io(
    cfg: WorldModelConfig,
    params: Params,
    deter: jax.Array,
    eproj: jax.Array,
    taps: Taps | None = None,
) -> tuple[dict[str, jax.Array], dict[str, jax.Array]]:
    """Posterior ``q(s | h, e)`` statistics ``Dense(act(Dense_h(h) + Dense_e(e)))``, plus the
    inputs of the two dense layers applied to ``h`` (``obs_h: [..., D]``, ``obs_out: [..., hidden]``)."""
    mods = _rssm_nets(cfg)
    act = nets.ACTIVATIONS[cfg.act]
    x = act(_add(_apply(mods["obs_h"], params["obs_h"], deter), taps, "obs_h") + eproj)
    raw = _add(_apply(mods["obs_out"], params["obs_out"], x), taps, "obs_out")
    return _stats(cfg, raw), {"obs_h": deter, "obs_out": x}


def _post_stats(
    cfg: WorldModelConfig, params: Params, deter: jax.Array, eproj: jax.Array
) -> dict[str, jax.Array]:
    return _post_stats_io(cfg, params, deter, eproj)[0]


def _reset(state: RSSMState, action: jax.Array, is_first: jax.Array) -> tuple[RSSMState, jax.Array]:
    """Zero the previous state and action where ``is_first: [...]`` is set."""
    keep = lambda x: jnp.where(
        is_first.reshape(is_first.shape + (1,) * (x.ndim - is_first.ndim)), 0, x
    )
    return state.replace(deter=keep(state.deter), stoch=keep(state.stoch)), keep(action)


def img_step(
    cfg: WorldModelConfig, params: Params, state: RSSMState, action: jax.Array, key: jax.Array
) -> RSSMState:
    """Stochastic prior step ``p(s', h' | s, h, a)``; state ``[..., ]``, action ``[..., A]``."""
    deter = _transition(cfg, params, state.stoch, state.deter, action)
    stats = prior_stats(cfg, params, deter)
    stoch = _sample(cfg, stats, _noise(cfg, key, deter.shape[:-1]))
    return RSSMState(deter=deter, stoch=stoch, stats=stats)


def img_step_mean(
    cfg: WorldModelConfig, params: Params, state: RSSMState, action: jax.Array
) -> RSSMState:
    """Deterministic prior step: ``s' = m(h')`` (LatCo's F_mu on the state pytree)."""
    deter = _transition(cfg, params, state.stoch, state.deter, action)
    stats = prior_stats(cfg, params, deter)
    return RSSMState(deter=deter, stoch=dist_mean(cfg, stats), stats=stats)


def obs_step(
    cfg: WorldModelConfig,
    params: Params,
    prev: RSSMState,
    prev_action: jax.Array,
    obs: jax.Array,
    is_first: jax.Array,
    key: jax.Array,
) -> tuple[RSSMState, RSSMState]:
    """One posterior filtering step (the agent's per-step verb).

    Args: prev ``[B]`` state; prev_action ``a_{t-1}: [B, A]``; obs ``o_t: [B, *obs_shape]`` raw;
    is_first ``[B]`` (resets prev state and action to zeros); key for this step.
    Returns (posterior, prior) at t, each ``[B]``. The batch may be empty (``()``).
    """
    prev, prev_action = _reset(prev, prev_action, is_first)
    deter = _transition(cfg, params, prev.stoch, prev.deter, prev_action)
    eproj = _embed_proj(cfg, params, encode(cfg, params, obs))
    post = _post_stats(cfg, params, deter, eproj)
    stoch = _sample(cfg, post, _noise(cfg, key, deter.shape[:-1]))
    prior = prior_stats(cfg, params, deter)
    prior_state = RSSMState(deter=deter, stoch=dist_mean(cfg, prior), stats=prior)
    return RSSMState(deter=deter, stoch=stoch, stats=post), prior_state


def _step_noise(cfg: WorldModelConfig, key: jax.Array, steps: int, batch: tuple[int, ...]):
    """Noise for ``steps`` consecutive steps, ``[steps, *batch, ...]``; step t uses
    ``split(key, steps)[t]`` exactly as the single-step verbs would."""
    return jax.vmap(lambda k: _noise(cfg, k, batch))(jax.random.split(key, steps))


def _time_major(x: jax.Array) -> jax.Array:
    return jnp.swapaxes(x, 0, 1)


def observe(
    cfg: WorldModelConfig,
    params: Params,
    obs: jax.Array,
    action: jax.Array,
    is_first: jax.Array,
    key: jax.Array,
    state: RSSMState | None = None,
    unroll: int | bool = 1,
) -> tuple[RSSMState, RSSMState]:
    """Posterior filtering over a sequence (``lax.scan`` over time).

    Args: obs ``[B, T, *obs_shape]``; action ``a_{t-1}: [B, T, A]``; is_first ``[B, T]``;
    key (step t uses ``split(key, T)[t]``, matching :func:`obs_step`); state: the state before
    step 0 (``[B]``; default zeros); unroll: scan unroll factor (static).
    Returns (posterior, prior), each ``[B, T]``; the prior's stoch is its mean.
    """
    post, prior, _ = _observe_io(cfg, params, obs, action, is_first, key, state, unroll)
    return post, prior


def _stop_dense(params: Params) -> Params:
    """Stop the gradient of the scanned dense layers' kernels and biases (they get theirs from
    the taps, :func:`_grads`); other parameters (e.g. the GRU's LayerNorm) are untouched."""
    out = dict(params)
    for name in RECURRENT:
        out[name] = {**params[name], "Dense_0": jax.lax.stop_gradient(params[name]["Dense_0"])}
    return out


def _observe_io(
    cfg: WorldModelConfig,
    params: Params,
    obs: jax.Array,
    action: jax.Array,
    is_first: jax.Array,
    key: jax.Array,
    state: RSSMState | None = None,
    unroll: int | bool = 1,
    taps: Taps | None = None,
) -> tuple[RSSMState, RSSMState, dict[str, jax.Array]]:
    """:func:`observe`, also returning the inputs of the scanned dense layers (time-major,
    ``[T, B, in]`` per name in :data:`RECURRENT`). With ``taps`` (``[T, B, out]`` zeros per name)
    those layers' weights are stop-gradient and the taps carry their output cotangents."""
    batch, steps = is_first.shape
    state = initial_state(cfg, (batch,)) if state is None else state
    eproj = _time_major(_embed_proj(cfg, params, encode(cfg, params, obs)))  # [T, B, hidden]
    first = _time_major(is_first)
    action = jnp.where(first[..., None], 0.0, _time_major(action).astype(jnp.float32))
    noise = _step_noise(cfg, key, steps, (batch,))
    rparams = params if taps is None else _stop_dense(params)

    def body(carry, xs):
        stoch, deter = carry
        a, ep, f, n, tap = xs
        stoch = jnp.where(f[:, None], 0.0, stoch)
        deter = jnp.where(f[:, None], 0.0, deter)
        deter, ins = _transition_io(cfg, rparams, stoch, deter, a, tap)
        stats, ins_post = _post_stats_io(cfg, rparams, deter, ep, tap)
        stoch = _sample(cfg, stats, n)
        return (stoch, deter), (stoch, deter, stats, {**ins, **ins_post})

    carry = (state.stoch, state.deter)
    xs = (action, eproj, first, noise, taps)
    _, (stoch, deter, stats, inputs) = jax.lax.scan(body, carry, xs, unroll=unroll)
    post = jax.tree.map(_time_major, RSSMState(deter=deter, stoch=stoch, stats=stats))
    prior = prior_stats(cfg, params, post.deter)
    prior_state = RSSMState(deter=post.deter, stoch=dist_mean(cfg, prior), stats=prior)
    return post, prior_state, inputs


def _batch_leading(state: RSSMState, batch_ndim: int) -> RSSMState:
    """``[T, *batch, ...] -> [*batch, T, ...]`` for every leaf."""
    return jax.tree.map(lambda x: jnp.moveaxis(x, 0, batch_ndim), state)


def imagine(
    cfg: WorldModelConfig,
    params: Params,
    start: RSSMState,
    actions: jax.Array,
    key: jax.Array,
) -> RSSMState:
    """Open-loop prior rollout from ``start [*batch]`` under ``actions: [*batch, H, A]``.

    Step k uses ``split(key, H)[k]`` exactly as :func:`img_step`. Returns states ``[*batch, H]``
    for k = 1..H (the start state is not included).
    """
    batch = start.deter.shape[:-1]
    horizon = actions.shape[-2]
    acts = jnp.moveaxis(actions, -2, 0)
    noise = _step_noise(cfg, key, horizon, batch)

    def body(state, xs):
        a, n = xs
        deter = _transition(cfg, params, state.stoch, state.deter, a)
        stats = prior_stats(cfg, params, deter)
        nxt = RSSMState(deter=deter, stoch=_sample(cfg, stats, n), stats=stats)
        return nxt, nxt

    _, states = jax.lax.scan(body, start, (acts, noise))
    return _batch_leading(states, len(batch))


def imagine_policy(
    cfg: WorldModelConfig,
    params: Params,
    start: RSSMState,
    policy: Callable[[jax.Array, jax.Array], jax.Array],
    horizon: int,
    key: jax.Array,
) -> tuple[RSSMState, jax.Array]:
    """Closed-loop prior rollout: ``a_k = policy(sg(f_k), key_k)``, then ``img_step``.

    Returns (states ``[*batch, H]`` for k = 1..H, actions ``[*batch, H, A]`` for k = 0..H-1).
    """
    batch = start.deter.shape[:-1]

    def body(state, k):
        kp, ks = jax.random.split(k)
        a = policy(jax.lax.stop_gradient(get_feat(state)), kp)
        nxt = img_step(cfg, params, state, a, ks)
        return nxt, (nxt, a)

    _, (states, acts) = jax.lax.scan(body, start, jax.random.split(key, horizon))
    return _batch_leading(states, len(batch)), jnp.moveaxis(acts, 0, len(batch))

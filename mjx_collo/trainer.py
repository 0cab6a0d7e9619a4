"""The one-program trainer: ``make_train(cfg, env) -> Trainer`` with ``init``, ``chunk``, ``evaluate``.

A chunk is one XLA program doing ``U`` iterations (``lax.scan``) of

    act   : posterior filter -> planner (every ``mpc_steps``) or actor -> action   [E envs, vmapped]
    env   : MJX step x action_repeat                                                [vmapped]
    store : transition -> on-device replay
    learn : when due, K world-model (+ value / actor) updates                      [lax.fori_loop]

Seeds (and swept float hyperparameters) are an outer ``vmap`` over the whole program. The schedule
(iteration counter) is *not* batched over seeds: every ``lax.cond`` predicate (prefill, replan,
episode end, training due) derives from it alone, so under the seed vmap the conds stay real
branches instead of selects that would run planning and training every step.

All envs of a seed run synchronised fixed-length episodes (dm_control tasks never terminate), so
resets happen for all envs at once, at episode boundaries. A NaN-physics env ends its episode
(flagged, counted in ``env/nan``) and idles until the common boundary.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from mjx_collo import actor as actor_lib
from mjx_collo import agent as agent_lib
from mjx_collo import config as config_lib
from mjx_collo import flops as flops_lib
from mjx_collo import planner as planner_lib
from mjx_collo import replay as replay_lib
from mjx_collo import value as value_lib
from mjx_collo import world_model as wm_lib
from mjx_collo.config import Config, ConfigError

NAN = float("nan")


@struct.dataclass
class TrainState:
    """Everything one seed's run carries between chunks (a pytree; leading seed axis when stacked).

    ``hyper`` holds the swept float hyperparameters ({dotted key: []}); ``ep_return`` the running
    undiscounted return of each env's current episode; counters are int32 scalars.
    """

    wm: Any
    wm_opt: Any
    value: Any
    actor: Any
    wm_old: Any
    env: Any
    agent: agent_lib.AgentCarry
    replay: replay_lib.ReplayState
    key: jax.Array
    hyper: dict[str, jax.Array]
    ep_return: jax.Array
    updates: jax.Array
    nonfinite_streak: jax.Array
    nonfinite_total: jax.Array
    lam_ema: jax.Array


class Trainer(NamedTuple):
    """Pure functions of one seed (vmap/jit them; see :func:`batched`).

    init(key, hyper) -> TrainState; chunk(state, iteration) -> (state, metrics {k: [U]});
    evaluate(state, key) -> metrics (returns [episodes], qpos [T, nq] of episode 0);
    costs(state) -> matmul FLOPs of one acting step that plans (all ``num_envs`` envs) and of one
    update (:mod:`mjx_collo.flops`; ``state`` may be abstract). ``plan_every``: agent steps between
    planning calls (1 for the Dreamer actor, which acts every step).
    """

    cfg: Config
    init: Callable[..., TrainState]
    chunk: Callable[..., tuple[TrainState, dict[str, jax.Array]]]
    evaluate: Callable[..., dict[str, jax.Array]]
    iterations_per_chunk: int
    env_steps_per_iteration: int
    episode_agent_steps: int
    costs: Callable[..., dict[str, flops_lib.FlopCount]]
    plan_every: int


def validate(cfg: Config) -> None:
    """Static consistency checks with messages that name the fix."""
    run, env = cfg.run, cfg.env
    per_iter = run.num_envs * env.action_repeat
    if env.episode_env_steps % env.action_repeat:
        raise ConfigError(
            f"env.episode_env_steps={env.episode_env_steps} is not a multiple of "
            f"env.action_repeat={env.action_repeat}"
        )
    for name in ("chunk_env_steps", "prefill", "train_every"):
        value = getattr(run, name)
        if value % per_iter:
            raise ConfigError(
                f"run.{name}={value} must be a multiple of run.num_envs x env.action_repeat = "
                f"{per_iter} (env steps per iteration)"
            )
    for name in ("eval_every", "checkpoint_every"):
        value = getattr(run, name)
        if value % run.chunk_env_steps:
            raise ConfigError(
                f"run.{name}={value} must be a multiple of run.chunk_env_steps="
                f"{run.chunk_env_steps} (evaluation and checkpoints happen between chunks)"
            )
    pc = cfg.planner
    if pc.kind == "collodreamer" and cfg.value.bootstrap and pc.value_lambda < 1.0:
        if pc.solver != "adam":
            raise ConfigError(
                f"planner.value_lambda={pc.value_lambda} (a lambda-return over the plan) needs "
                f"planner.solver=adam; the {pc.solver} residuals bootstrap the value at the "
                f"plan's end only: add planner.value_lambda=1.0"
            )
    if run.prefill // per_iter < cfg.replay.length:
        raise ConfigError(
            f"run.prefill={run.prefill} env steps give {run.prefill // per_iter} replay rows per "
            f"env, fewer than replay.length={cfg.replay.length}; raise run.prefill"
        )


def make_train(cfg: Config, env: Any) -> Trainer:
    """Build the trainer for ``cfg`` on ``env`` (one unbatched env with action repeat and episode
    limit applied, actions in [-1, 1]: ``envs.make(task, action_repeat=R, episode_length=...,
    normalize_actions=True)``)."""
    validate(cfg)
    run = cfg.run
    num_envs, repeat = run.num_envs, cfg.env.action_repeat
    per_iter = num_envs * repeat
    episode_len = cfg.env.episode_env_steps // repeat
    iterations = run.chunk_env_steps // per_iter
    action_dim = int(env.action_size)
    obs_shape = (int(env.observation_size),)
    kind = cfg.planner.kind
    use_value = cfg.value.enabled
    use_actor = kind == "dreamer"
    value_mode = cfg.value.mode if use_value and not use_actor else "none"
    if cfg.j_latent.enabled and not use_value:
        raise ConfigError("j_latent.enabled needs a value network (value.enabled=true)")
    if value_mode in ("plan_inner", "plan_final") and kind not in planner_lib.COLLOCATION:
        raise ConfigError(
            f"value.mode={value_mode} trains the value on plans, which needs a collocation "
            f"planner (latco or collodreamer), not planner.kind={kind}; use value.mode=replay"
        )
    feat_dim = wm_lib.feat_size(cfg.wm)

    def configured(state: TrainState) -> tuple[Config, agent_lib.Agent]:
        """Config with this seed's swept values (tracers) and the agent built from it."""
        c = config_lib.with_values(cfg, state.hyper)
        return c, agent_lib.make_agent(c, action_dim)

    # ---- init ----------------------------------------------------------------------------------

    def init(key: jax.Array, hyper: dict[str, jax.Array]) -> TrainState:
        c = config_lib.with_values(cfg, hyper)
        k_wm, k_val, k_act, k_env, k_agent, key = jax.random.split(key, 6)
        wm = wm_lib.init(c.wm, k_wm, obs_shape, action_dim)
        vstate = value_lib.init_value(c.value, k_val, feat_dim) if use_value else None
        astate = actor_lib.init_actor(c.actor, k_act, feat_dim, action_dim) if use_actor else None
        env_state = jax.vmap(env.reset)(jax.random.split(k_env, num_envs))
        agent = agent_lib.make_agent(c, action_dim)
        vt = vstate.target if vstate is not None else None
        carry = agent_lib.init_carry(agent, agent_lib.plan_params(wm, vt), num_envs, k_agent)
        replay = replay_lib.init(
            c.replay, num_envs, repeat, replay_lib.default_fields(obs_shape, action_dim)
        )
        replay = replay_lib.add(replay, _first_row(env_state.obs))
        return TrainState(
            wm=wm,
            wm_opt=wm_lib.init_opt_state(c.wm, wm),
            value=vstate,
            actor=astate,
            wm_old=wm if c.j_latent.enabled else None,
            env=env_state,
            agent=carry,
            replay=replay,
            key=key,
            hyper=dict(hyper),
            ep_return=jnp.zeros((num_envs,), jnp.float32),
            updates=jnp.zeros((), jnp.int32),
            nonfinite_streak=jnp.zeros((), jnp.int32),
            nonfinite_total=jnp.zeros((), jnp.int32),
            lam_ema=jnp.ones((), jnp.float32),
        )

    def _first_row(obs: jax.Array) -> dict[str, jax.Array]:
        n = obs.shape[0]
        return {
            "obs": obs,
            "action": jnp.zeros((n, action_dim), jnp.float32),
            "reward": jnp.zeros((n,), jnp.float32),
            "is_first": jnp.ones((n,), bool),
        }

    # ---- acting ---------------------------------------------------------------------------------

    def plan_metric_shapes(s: TrainState) -> dict[str, jax.ShapeDtypeStruct]:
        if use_actor:
            return {}
        return jax.eval_shape(
            lambda st, k: _policy(st, k, jnp.zeros((), jnp.int32), True)[2],
            s,
            jax.random.PRNGKey(0),
        )

    def _policy(s: TrainState, key: jax.Array, t: jax.Array, training: bool):
        """Filter the posterior, replan when due (unbatched t), act. -> (a, s, plan metrics)."""
        c, agent = configured(s)
        k_obs, k_plan, k_act = jax.random.split(key, 3)
        first = jnp.broadcast_to(t == 0, (num_envs,))
        carry = agent_lib.observe(agent, s.wm, s.agent, s.env.obs, first, k_obs)
        vstate = s.value
        metrics: dict[str, jax.Array] = {}
        if not use_actor:
            vt = vstate.target if vstate is not None else None
            params = agent_lib.plan_params(s.wm, vt)

            def do_plan(operand):
                carry, vstate = operand
                if value_mode == "plan_inner":
                    carry, m, vstate = agent_lib.replan_inner(agent, params, carry, vstate, k_plan)
                else:
                    carry, m = agent_lib.replan(agent, params, carry, k_plan)
                    if value_mode == "plan_final":
                        acts = jax.vmap(agent.planner.actions)(carry.mpc.plan)
                        batch = planner_lib.plan_value_batch(agent.model, params, carry.post, acts)
                        vstate, vm = value_lib.train_step(c.value, vstate, batch, k_plan)
                        m = {**m, **{f"plan_{k}": v for k, v in vm.items()}}
                return (carry, vstate), {f"plan/{k}": v for k, v in m.items()}

            def no_plan(operand):
                shapes = jax.eval_shape(do_plan, operand)[1]
                return operand, {k: jnp.full(v.shape, NAN, v.dtype) for k, v in shapes.items()}

            (carry, vstate), metrics = jax.lax.cond(
                t % agent.cache_len == 0, do_plan, no_plan, (carry, vstate)
            )
        actor_params = s.actor.params if use_actor else None
        a, carry = agent_lib.act(agent, actor_params, carry, k_act, training)
        if use_actor and training:
            noise = c.explore.noise * jax.random.normal(k_act, a.shape)
            a = jnp.clip(a + noise, -1.0, 1.0)
            carry = carry.replace(prev_action=a)
        return a, s.replace(agent=carry, value=vstate), metrics

    # ---- learning -------------------------------------------------------------------------------

    def _update(s: TrainState, key: jax.Array) -> tuple[TrainState, dict[str, jax.Array]]:
        """One world-model update (+ value on replay posteriors, or actor-critic)."""
        c, _ = configured(s)
        k_batch, k_wm, k_v = jax.random.split(key, 3)
        batch = replay_lib.sample(s.replay, k_batch, c.replay.batch, c.replay.length)
        jlat = None
        if c.j_latent.enabled:
            # beta_lat = beta0 / lambda_bar: the weight falls as the planner's dynamics
            # multipliers grow (ALGORITHM.md §4.5); lambda_bar is an EMA of the plan mean.
            target = s.value.target
            jlat = wm_lib.JLatentArgs(
                old_params=s.wm_old,
                value_fn=lambda f: value_lib.apply_value(c.value, target, f),
                beta=c.j_latent.beta0 / jnp.maximum(s.lam_ema, 1.0),
                gamma=c.value.gamma,
                cfg=c.j_latent,
            )
        wm, wm_opt, wm_m, post = wm_lib.train_step(c.wm, s.wm, s.wm_opt, batch, k_wm, jlat)
        metrics = {f"wm/{k}": v for k, v in wm_m.items()}
        vstate, astate = s.value, s.actor
        if use_actor:
            starts = actor_lib.flatten_starts(post.state, 2)
            imag = agent_lib.imagination_model(c)
            astate, vstate, am = actor_lib.train_step(c, imag, wm, astate, vstate, starts, k_v)
            metrics.update(am)
        elif value_mode == "replay":
            vbatch = {"feat": post.feat, "reward": post.reward, "is_first": post.is_first}
            vstate, vm = value_lib.train_step(c.value, vstate, vbatch, k_v)
            metrics.update(vm)
        bad = wm_m["nonfinite"] > 0
        streak = jnp.where(bad, s.nonfinite_streak + 1, 0)
        wm_old = s.wm_old
        if c.j_latent.enabled:
            refresh = (s.updates + 1) % c.j_latent.old_every == 0
            wm_old = jax.tree.map(lambda n, o: jnp.where(refresh, n, o), wm, s.wm_old)
        s = s.replace(
            wm=wm,
            wm_opt=wm_opt,
            value=vstate,
            actor=astate,
            wm_old=wm_old,
            updates=s.updates + 1,
            nonfinite_streak=streak,
            nonfinite_total=s.nonfinite_total + bad.astype(jnp.int32),
        )
        return s, metrics

    def _learn(s: TrainState, key: jax.Array, n: jax.Array):
        """``n`` (unbatched) updates; metrics are means over them."""
        shapes = jax.eval_shape(_update, s, key)[1]
        zeros = {k: jnp.zeros(v.shape, jnp.float32) for k, v in shapes.items()}

        def body(i, carry):
            s, sums = carry
            s, m = _update(s, jax.random.fold_in(key, i))
            return s, {k: sums[k] + m[k].astype(jnp.float32) for k in sums}

        s, sums = jax.lax.fori_loop(0, n, body, (s, zeros))
        return s, {k: v / jnp.maximum(n, 1).astype(jnp.float32) for k, v in sums.items()}

    # Each of these is traced several times per program (for output shapes, then in both
    # branches of a lax.cond, then again for evaluation); as jitted functions with one identity
    # the later traces come from JAX's cache. XLA inlines them, so the compiled program is the same.
    _policy = jax.jit(_policy, static_argnums=3)
    _update = jax.jit(_update)
    _learn = jax.jit(_learn)

    # ---- one iteration --------------------------------------------------------------------------

    def iteration(carry, _):
        s, it = carry
        t = it % episode_len  # agent step within the (synchronised) episode
        env_step = it * per_iter
        key, k_pol, k_rand, k_reset, k_learn = jax.random.split(s.key, 5)
        s = s.replace(key=key)

        # act
        prefill = env_step < run.prefill
        plan_shapes = plan_metric_shapes(s)

        def explore(s):
            a = jax.random.uniform(k_rand, (num_envs, action_dim), minval=-1.0, maxval=1.0)
            s = s.replace(agent=s.agent.replace(prev_action=a))
            return a, s, {k: jnp.full(v.shape, NAN, v.dtype) for k, v in plan_shapes.items()}

        def policy(s):
            return _policy(s, k_pol, t, True)

        a, s, plan_m = jax.lax.cond(prefill, explore, policy, s)
        if "plan/lam_mean" in plan_m:
            lam = plan_m["plan/lam_mean"]
            s = s.replace(
                lam_ema=jnp.where(jnp.isfinite(lam), 0.99 * s.lam_ema + 0.01 * lam, s.lam_ema)
            )

        # env step (action repeat inside) and store the transition
        env_state = jax.vmap(env.step)(s.env, a)
        ep_return = s.ep_return + env_state.reward
        replay = replay_lib.add(
            s.replay,
            {
                "obs": env_state.obs,
                "action": a,
                "reward": env_state.reward,
                "is_first": jnp.zeros((num_envs,), bool),
            },
        )
        nan_envs = jnp.sum(env_state.metrics["nan"])
        s = s.replace(env=env_state, replay=replay, ep_return=ep_return)

        # episode boundary: log returns, reset every env, store the first observations
        last = t == episode_len - 1
        train_return = jnp.where(last, jnp.mean(ep_return), NAN)

        def new_episode(s):
            c, agent = configured(s)
            env_state = jax.vmap(env.reset)(jax.random.split(k_reset, num_envs))
            return s.replace(
                env=env_state,
                replay=replay_lib.add(s.replay, _first_row(env_state.obs)),
                agent=agent_lib.reset_carry(agent, s.agent),
                ep_return=jnp.zeros_like(s.ep_return),
            )

        s = jax.lax.cond(last, new_episode, lambda s: s, s)

        # learn on schedule (env steps include action repeat; first call = pretrain updates)
        after = env_step + per_iter
        crossed = after // run.train_every > env_step // run.train_every
        first_call = (env_step < run.prefill) & (after >= run.prefill)
        due = (after >= run.prefill) & (crossed | first_call)
        n = jnp.where(first_call, run.pretrain, run.train_steps)
        learn_shapes = jax.eval_shape(lambda s: _learn(s, k_learn, n)[1], s)

        def skip(s):
            return s, {k: jnp.full(v.shape, NAN, v.dtype) for k, v in learn_shapes.items()}

        s, learn_m = jax.lax.cond(due, lambda s: _learn(s, k_learn, n), skip, s)

        metrics = {
            "train/return": train_return,
            "env/nan": nan_envs.astype(jnp.float32),
            **plan_m,
            **learn_m,
            "train/nonfinite_streak": s.nonfinite_streak.astype(jnp.float32),
        }
        return (s, it + 1), metrics

    def chunk(s: TrainState, it: jax.Array) -> tuple[TrainState, dict[str, jax.Array]]:
        """``iterations_per_chunk`` iterations from schedule position ``it`` (unbatched int32)."""
        (s, _), metrics = jax.lax.scan(iteration, (s, it), None, length=iterations)
        return s, metrics

    # ---- evaluation -----------------------------------------------------------------------------

    def evaluate(s: TrainState, key: jax.Array) -> dict[str, jax.Array]:
        """``run.eval_episodes`` deterministic episodes (no noise, clipped actions) with the current
        parameters; nothing is stored. Returns returns [episodes] and episode 0's qpos [T, nq]."""
        n = cfg.run.eval_episodes
        c, agent = configured(s)
        k_env, k_carry, key = jax.random.split(key, 3)
        env_state = jax.vmap(env.reset)(jax.random.split(k_env, n))
        vt = s.value.target if s.value is not None else None
        params = agent_lib.plan_params(s.wm, vt)
        carry = agent_lib.init_carry(agent, params, n, k_carry)
        actor_params = s.actor.params if use_actor else None

        def step(carry_all, t):
            env_state, carry, ret = carry_all
            k = jax.random.fold_in(key, t)
            k_obs, k_plan, k_act = jax.random.split(k, 3)
            first = jnp.broadcast_to(t == 0, (n,))
            carry = agent_lib.observe(agent, s.wm, carry, env_state.obs, first, k_obs)
            if not use_actor:
                carry = jax.lax.cond(
                    t % agent.cache_len == 0,
                    lambda cr: agent_lib.replan(agent, params, cr, k_plan)[0],
                    lambda cr: cr,
                    carry,
                )
            a, carry = agent_lib.act(agent, actor_params, carry, k_act, training=False)
            env_state = jax.vmap(env.step)(env_state, a)
            qpos = env_state.pipeline_state.qpos[0]
            return (env_state, carry, ret + env_state.reward), qpos

        (env_state, _, returns), qpos = jax.lax.scan(
            step, (env_state, carry, jnp.zeros((n,))), jnp.arange(episode_len)
        )
        out = {"returns": returns, "qpos": qpos}
        if "target_xy" in env_state.info:
            out["target_xy"] = env_state.info["target_xy"][0]
        return out

    # ---- cost ---------------------------------------------------------------------------------

    def costs(s: TrainState) -> dict[str, flops_lib.FlopCount]:
        """Matmul FLOPs of an acting step at a planning step (t = 0: observe, plan, act for all
        envs) and of one update, loops counted per iteration (XLA's count takes each loop body
        once, so its figure for a chunk is that of one iteration)."""
        key = jax.random.PRNGKey(0)
        t0 = jnp.zeros((), jnp.int32)
        return {
            "act": flops_lib.matmul_flops(lambda st, k: _policy(st, k, t0, True)[0], s, key),
            "update": flops_lib.matmul_flops(lambda st, k: _update(st, k)[0], s, key),
        }

    return Trainer(
        cfg=cfg,
        init=init,
        chunk=chunk,
        evaluate=evaluate,
        iterations_per_chunk=iterations,
        env_steps_per_iteration=per_iter,
        episode_agent_steps=episode_len,
        costs=costs,
        plan_every=agent_lib.make_agent(cfg, action_dim).cache_len,
    )


# ------------------------------------------------------------------------------------------------
# Seeds, sweeps and sharding
# ------------------------------------------------------------------------------------------------


def seed_keys(cfg: Config, num_seeds: int) -> jax.Array:
    """Independent keys for ``num_seeds`` seeds from ``run.seed`` ([S, 2])."""
    base = jax.random.PRNGKey(cfg.run.seed)
    return jax.vmap(lambda i: jax.random.fold_in(base, i))(jnp.arange(num_seeds))


def sweep_grid(
    sweep: dict[str, list[float]], seeds: int
) -> tuple[int, dict[str, jax.Array], list[dict[str, float]]]:
    """Cartesian product of swept values x seeds -> (S total, hyper {key: [S]}, per-run labels)."""
    keys = sorted(sweep)
    combos: list[dict[str, float]] = [{}]
    for k in keys:
        combos = [{**c, k: v} for c in combos for v in sweep[k]]
    labels = [dict(c, seed=i) for c in combos for i in range(seeds)]
    hyper = {k: jnp.asarray([lab[k] for lab in labels], jnp.float32) for k in keys}
    return len(labels), hyper, labels


def mesh_sharding(num_seeds: int):
    """NamedSharding of the seed axis over all devices (None if 1 device or not divisible)."""
    devices = jax.devices()
    if jax.process_count() > 1 and num_seeds % len(devices):
        raise ConfigError(
            f"{num_seeds} run(s) cannot be split over the {len(devices)} devices of "
            f"{jax.process_count()} processes: use a multiple of {len(devices)} seeds x sweep values"
        )
    if len(devices) < 2 or num_seeds % len(devices):
        return None
    import numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    mesh = Mesh(np.array(devices), ("seed",))
    return NamedSharding(mesh, PartitionSpec("seed"))


def replicated(sharding):
    """The same mesh as ``sharding`` with every array replicated (schedule counters)."""
    return jax.sharding.NamedSharding(sharding.mesh, jax.sharding.PartitionSpec())


def over_seeds(f: Callable, in_axes: tuple[int | None, ...]) -> Callable:
    """``vmap(f, in_axes)`` over the seed axis, except that one seed runs unbatched.

    With a seed axis of size 1, vmap turns every matmul against the seed's weights into a
    batched dot, which XLA's CPU backend runs markedly slower than the plain one (one default
    planning call on 2 cores: 810 ms vmapped over one seed, 560 ms unbatched). One seed is the
    common case (``make train``), so this drops the axis, calls ``f`` directly and puts the axis
    back (reshapes only).
    """
    vf = jax.vmap(f, in_axes=in_axes)

    def g(*args):
        sizes = {
            x.shape[0]
            for a, ax in zip(args, in_axes, strict=True)
            if ax == 0
            for x in jax.tree.leaves(a)
        }
        if sizes != {1}:
            return vf(*args)
        pairs = zip(args, in_axes, strict=True)
        one = [jax.tree.map(lambda x: x[0], a) if ax == 0 else a for a, ax in pairs]
        return jax.tree.map(lambda x: x[None], f(*one))

    return g


def batched(trainer: Trainer, sharding=None):
    """jit(vmap) of init / chunk / evaluate over the seed axis (state donated into chunk).

    With a seed sharding the functions run under ``shard_map``: each device runs its own block of
    seeds through :func:`over_seeds`, so a device holding one seed runs it unbatched. Seeds never
    communicate, so the program has no collectives. Under plain ``jit`` sharding propagation
    would keep the seed axis as a batch dimension of size 1 on every device: the slow batched
    dot that :func:`over_seeds` avoids (one default planning call, 2 seeds on 2 forced CPU
    devices: 557 ms sharded with jit, 320 ms with shard_map, 406 ms on one device).
    """
    init = over_seeds(trainer.init, (0, 0))
    chunk = over_seeds(trainer.chunk, (0, None))
    evaluate = over_seeds(trainer.evaluate, (0, 0))
    if sharding is None:
        return (jax.jit(init), jax.jit(chunk, donate_argnums=0), jax.jit(evaluate))
    from jax.sharding import PartitionSpec

    seed, rep = PartitionSpec("seed"), PartitionSpec()

    def per_device(f, in_specs, out_specs):
        # check_vma=False: the per-seed code's loops carry values the checker cannot type
        # (fresh constants next to per-device data); nothing here is reduced across devices.
        return jax.shard_map(
            f, mesh=sharding.mesh, in_specs=in_specs, out_specs=out_specs, check_vma=False
        )

    rep_sharding = replicated(sharding)
    return (
        jax.jit(
            per_device(init, (seed, seed), seed),
            in_shardings=(sharding, sharding),
            out_shardings=sharding,
        ),
        jax.jit(
            per_device(chunk, (seed, rep), (seed, seed)),
            in_shardings=(sharding, rep_sharding),
            out_shardings=(sharding, sharding),
            donate_argnums=0,
        ),
        jax.jit(
            per_device(evaluate, (seed, seed), seed),
            in_shardings=(sharding, sharding),
            out_shardings=sharding,
        ),
    )


def matmul_budget(trainer: Trainer, costs: dict[str, flops_lib.FlopCount]) -> dict[str, float]:
    """GFLOP of matmul work by schedule, from :attr:`Trainer.costs`: one planning call per env,
    one update, a steady chunk (after the prefill), one evaluation, and the whole run.

    Acting steps between planning calls (posterior filter, cached action) are not counted: next
    to a planning call they are negligible (for the Dreamer actor every step is counted).
    """
    run = trainer.cfg.run
    act, upd = costs["act"].gflops, costs["update"].gflops
    per_env = act / run.num_envs
    calls_per_chunk = trainer.iterations_per_chunk / trainer.plan_every
    updates_per_chunk = run.chunk_env_steps / run.train_every * run.train_steps
    chunk = calls_per_chunk * act + updates_per_chunk * upd
    evaluation = trainer.episode_agent_steps / trainer.plan_every * run.eval_episodes * per_env
    acting_steps = max(run.steps - run.prefill, 0)
    calls = acting_steps / (trainer.env_steps_per_iteration * trainer.plan_every)
    updates = run.pretrain + acting_steps / run.train_every * run.train_steps
    evals = run.steps // run.eval_every
    return {
        "plan_call_gflop_per_env": per_env,
        "update_gflop": upd,
        "chunk_gflop": chunk,
        "eval_gflop": evaluation,
        "run_gflop": calls * act + updates * upd + evals * evaluation,
        "run_planning_share": (calls * act + evals * evaluation)
        / max(calls * act + updates * upd + evals * evaluation, 1e-9),
    }


def cost_summary(compiled) -> dict[str, float]:
    """Memory of a compiled program (XLA memory analysis). Its FLOPs: :func:`matmul_budget`
    (XLA's cost analysis counts each loop body once)."""
    out: dict[str, float] = {}
    try:
        mem = compiled.memory_analysis()
        out["temp_mib"] = mem.temp_size_in_bytes / 2**20
        out["args_mib"] = mem.argument_size_in_bytes / 2**20
    except Exception:  # noqa: BLE001
        pass
    return out

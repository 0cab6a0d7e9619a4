"""The one-program trainer: ``make_train(cfg, env) -> Trainer`` with ``init``, ``chunk``, ``evaluate``.

A chunk is one XLA program doing ``U`` iterations (``lax.scan``) of

    act   : posterior filter -> planner (every ``cache_len`` steps) or actor   [rollout.py]
    env   : MJX step x action_repeat -> replay; episode ends reset every env     [rollout.py]
    learn : when due, K world-model (+ value / actor) updates                   [learner.py]

Seeds (and swept float hyperparameters) are an outer ``vmap`` over the whole program. The schedule
(iteration counter) is *not* batched over seeds: every ``lax.cond`` predicate (prefill, replan,
episode end, training due) derives from it alone, so under the seed vmap the conds stay real
branches instead of selects that would run planning and training every step.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp

from mjx_collo import agent as agent_lib
from mjx_collo import config as config_lib
from mjx_collo import flops as flops_lib
from mjx_collo import planner as planner_lib
from mjx_collo.config import Config, ConfigError
from mjx_collo.learner import make_learner
from mjx_collo.rollout import NAN, make_rollout
from mjx_collo.train_state import TrainState

__all__ = ["TrainState", "Trainer", "make_train", "validate"]


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
    if cfg.value.enabled and cfg.value.mode == "plan_inner" and cfg.value.v_every > pc.iters:
        raise ConfigError(
            f"value.mode=plan_inner steps the value every value.v_every={cfg.value.v_every} "
            f"solver iterations, but a planning call runs planner.iters={pc.iters}: the value "
            f"would never learn; set value.v_every <= {pc.iters}"
        )
    config_lib.check_prior(cfg)
    config_lib.check_explore(cfg)
    if run.prefill // per_iter < cfg.replay.length:
        raise ConfigError(
            f"run.prefill={run.prefill} env steps give {run.prefill // per_iter} replay rows per "
            f"env, fewer than replay.length={cfg.replay.length}; raise run.prefill"
        )


def make_train(cfg: Config, env) -> Trainer:
    """Build the trainer for ``cfg`` on ``env`` (one unbatched env with action repeat and episode
    limit applied, actions in [-1, 1]: ``envs.from_config(cfg.env)``)."""
    validate(cfg)
    run = cfg.run
    num_envs = run.num_envs
    per_iter = num_envs * cfg.env.action_repeat
    episode_len = cfg.env.episode_env_steps // cfg.env.action_repeat
    iterations = run.chunk_env_steps // per_iter
    action_dim = int(env.action_size)
    obs_spec = jax.eval_shape(
        env.reset, jax.random.PRNGKey(0)
    ).obs  # [obs] float32 or [64, 64, 3] uint8
    obs_shape = tuple(obs_spec.shape)
    uses_actor = cfg.planner.kind == "dreamer"
    value_mode = cfg.value.mode if cfg.value.enabled and not uses_actor else "none"
    if cfg.j_latent.enabled and not cfg.value.enabled:
        raise ConfigError("j_latent.enabled needs a value network (value.enabled=true)")
    if (
        value_mode in ("plan_inner", "plan_final")
        and cfg.planner.kind not in planner_lib.COLLOCATION
    ):
        raise ConfigError(
            f"value.mode={value_mode} trains the value on plans, which needs a collocation "
            f"planner (latco or collodreamer), not planner.kind={cfg.planner.kind}; use value.mode=replay"
        )

    agent = agent_lib.make_agent(cfg, action_dim)

    def bind(hyper: dict[str, jax.Array]) -> tuple[Config, agent_lib.Agent]:
        """The config with this seed's swept values and its agent: the one built above, unless
        values are swept (then they are tracers and the agent is built from them)."""
        if not hyper:
            return cfg, agent
        c = config_lib.with_values(cfg, hyper)
        return c, agent_lib.make_agent(c, action_dim)

    learner = make_learner(cfg, obs_shape, action_dim, bind)
    rollout = make_rollout(cfg, env, bind, learner.value_on_plan)

    def init(key: jax.Array, hyper: dict[str, jax.Array]) -> TrainState:
        c, agent = bind(hyper)
        k_wm, k_val, k_act, k_env, k_agent, key = jax.random.split(key, 6)
        wm, wm_opt, vstate, astate, wm_old = learner.init(c, k_wm, k_val, k_act)
        vt = vstate.target if vstate is not None else None
        prior = astate.params if agent.uses_prior else None
        env_state, carry, replay = rollout.start(c, agent, wm, vt, k_env, k_agent, prior)
        return TrainState(
            wm=wm,
            wm_opt=wm_opt,
            value=vstate,
            actor=astate,
            wm_old=wm_old,
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
            explorer=learner.init_explorer(c, k_wm),
        )

    def iteration(carry, _):
        s, it = carry
        t = it % episode_len  # agent step within the (synchronised) episode
        env_step = it * per_iter
        key, k_pol, k_rand, k_reset, k_learn = jax.random.split(s.key, 5)
        s = s.replace(key=key)

        a, s, lam_mean, plan_m = rollout.act(s, k_pol, k_rand, t, env_step < run.prefill)
        s = learner.track_multipliers(s, lam_mean)
        s, nan_envs = rollout.step(s, a)
        last = t == episode_len - 1
        train_return = jnp.where(last, jnp.mean(s.ep_return), NAN)
        s = jax.lax.cond(last, rollout.end_episode, lambda s, k: s, s, k_reset)

        # learn on schedule (env steps include action repeat; the first call does the pretraining)
        after = env_step + per_iter
        crossed = after // run.train_every > env_step // run.train_every
        first_call = (env_step < run.prefill) & (after >= run.prefill)
        due = (after >= run.prefill) & (crossed | first_call)
        n = jnp.where(first_call, run.pretrain, run.train_steps)
        learn_shapes = jax.eval_shape(lambda s: learner.learn(s, k_learn, n)[1], s)

        def skip(s):
            return s, {k: jnp.full(v.shape, NAN, v.dtype) for k, v in learn_shapes.items()}

        s, learn_m = jax.lax.cond(due, lambda s: learner.learn(s, k_learn, n), skip, s)

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

    def costs(s: TrainState) -> dict[str, flops_lib.FlopCount]:
        """Matmul FLOPs of an acting step at a planning step (t = 0: observe, plan, act for all
        envs) and of one update, loops counted per iteration (XLA's count takes each loop body
        once, so its figure for a chunk is that of one iteration)."""
        key = jax.random.PRNGKey(0)
        t0 = jnp.zeros((), jnp.int32)
        return {
            "act": flops_lib.matmul_flops(lambda st, k: rollout.policy(st, k, t0, True)[0], s, key),
            "update": flops_lib.matmul_flops(lambda st, k: learner.update(st, k)[0], s, key),
        }

    return Trainer(
        cfg=cfg,
        init=init,
        chunk=chunk,
        evaluate=rollout.evaluate,
        iterations_per_chunk=iterations,
        env_steps_per_iteration=per_iter,
        episode_agent_steps=episode_len,
        costs=costs,
        plan_every=agent.cache_len,
    )

"""Acting in the envs: posterior filter -> planner (every ``cache_len`` steps) or Dreamer actor ->
action, the MJX env step with action repeat, storing the transition in the on-device replay, and
episode resets; plus deterministic evaluation episodes.

All envs of a seed run synchronised fixed-length episodes (dm_control tasks never terminate), so
resets happen for all envs at once, at episode boundaries. A NaN-physics env ends its episode
(flagged, counted in ``env/nan``) and idles until the common boundary.

*When* to plan, explore or reset is decided from the unbatched schedule (agent step ``t`` within
the episode), never from per-seed data, so under the seed vmap the ``lax.cond``s stay real
branches (see :mod:`mjx_collo.trainer`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from mjx_collo import agent as agent_lib
from mjx_collo import explorer as explorer_lib
from mjx_collo import planner as planner_lib
from mjx_collo import replay as replay_lib
from mjx_collo import world_model as wm_lib
from mjx_collo.config import Config
from mjx_collo.learner import Bind, PlanTargets, ValueOnPlan
from mjx_collo.train_state import TrainState

NAN = float("nan")


class Rollout(NamedTuple):
    """Pure functions of one seed (see :func:`make_rollout`)."""

    start: Callable[..., tuple[Any, agent_lib.AgentCarry, replay_lib.ReplayState]]
    act: Callable[..., tuple[jax.Array, TrainState, jax.Array, dict[str, jax.Array]]]
    step: Callable[[TrainState, jax.Array], tuple[TrainState, jax.Array]]
    end_episode: Callable[[TrainState, jax.Array], TrainState]
    evaluate: Callable[[TrainState, jax.Array], dict[str, jax.Array]]
    policy: Callable[..., tuple[jax.Array, TrainState, jax.Array, dict[str, jax.Array]]]


def run_replay_rows(cfg: Config) -> int:
    """The replay rows per env that a run of ``cfg.run.steps`` env steps (whole chunks) writes:
    the replay never holds more (replay.rows_per_env)."""
    per_iter = cfg.run.num_envs * cfg.env.action_repeat
    chunk = cfg.run.chunk_env_steps
    iterations = -(-cfg.run.steps // chunk) * chunk // per_iter
    return replay_lib.run_rows(iterations, cfg.env.episode_env_steps // cfg.env.action_repeat)


def make_rollout(cfg: Config, env: Any, bind: Bind, value_on_plan: ValueOnPlan) -> Rollout:
    """Acting for ``cfg`` on ``env`` (one unbatched env, action repeat and episode limit applied,
    actions in [-1, 1]); ``bind(hyper) -> (config with the swept values, Agent)``;
    ``value_on_plan``: the learner's value step on a plan's targets (``value.mode=plan_final``),
    taken right after the planning call that made them."""
    num_envs = cfg.run.num_envs
    episode_len = cfg.env.episode_env_steps // cfg.env.action_repeat
    action_dim = int(env.action_size)
    uses_actor = cfg.planner.kind == "dreamer"
    value_mode = cfg.value.mode if cfg.value.enabled and not uses_actor else "none"
    replay_rows = run_replay_rows(cfg)

    def first_row(obs: jax.Array) -> dict[str, jax.Array]:
        n = obs.shape[0]
        return {
            "obs": obs,
            "action": jnp.zeros((n, action_dim), jnp.float32),
            "reward": jnp.zeros((n,), jnp.float32),
            "is_first": jnp.ones((n,), bool),
        }

    def start(c: Config, agent, wm, value_target, k_env, k_agent, prior=None):
        """Reset the envs, start the agent's carry and a replay holding the first observations
        (``prior``: the policy prior's params, when the planner starts from it)."""
        env_state = jax.vmap(env.reset)(jax.random.split(k_env, num_envs))
        params = wm_lib.plan_params(wm, value_target, prior)
        carry = agent_lib.init_carry(agent, params, num_envs, k_agent)
        obs_shape = tuple(env_state.obs.shape[1:])
        replay = replay_lib.init(
            c.replay,
            num_envs,
            c.env.action_repeat,
            replay_lib.default_fields(obs_shape, action_dim, env_state.obs.dtype),
            run=replay_rows,
        )
        return env_state, carry, replay_lib.add(replay, first_row(env_state.obs))

    def _policy(s: TrainState, key: jax.Array, t: jax.Array, training: bool):
        """Filter the posterior, replan when due (unbatched t), act. -> (a, s, the plan's mean
        dynamics multiplier (NaN when no collocation plan was made), plan metrics)."""
        c, agent = bind(s.hyper)
        k_obs, k_plan, k_act = jax.random.split(key, 3)
        first = jnp.broadcast_to(t == 0, (num_envs,))
        carry = agent_lib.observe(agent, s.wm, s.agent, s.env.obs, first, k_obs)
        vstate = s.value
        metrics: dict[str, jax.Array] = {}
        lam = jnp.full((), NAN)
        if not uses_actor:
            vt = vstate.target if vstate is not None else None
            params = wm_lib.plan_params(s.wm, vt, s.actor.params if agent.uses_prior else None)

            def do_plan(operand):
                carry, vstate = operand
                if value_mode == "plan_inner":
                    carry, m, vstate = agent_lib.replan_inner(agent, params, carry, vstate, k_plan)
                else:
                    if training and agent.explore_planner is not None:
                        # training plans seek what the model cannot predict yet (explorer.py);
                        # the value still learns the task's returns of them (plan_final)
                        curious = (params, explorer_lib.bonus_params(s.explorer))
                        carry, m = agent_lib.replan(
                            agent, curious, carry, k_plan, agent.explore_planner
                        )
                    else:
                        carry, m = agent_lib.replan(agent, params, carry, k_plan)
                    if value_mode == "plan_final":
                        acts = jax.vmap(agent.planner.actions)(carry.mpc.plan)
                        batch = planner_lib.plan_value_batch(agent.model, params, carry.post, acts)
                        targets = PlanTargets(value_batch=batch, key=k_plan)
                        vstate, vm = value_on_plan(c, vstate, targets)
                        m = {**m, **vm}
                lam = m.get("lam_mean", jnp.full((), NAN))
                return (carry, vstate), lam, {f"plan/{k}": v for k, v in m.items()}

            def no_plan(operand):
                shapes = jax.eval_shape(do_plan, operand)[2]
                nan = {k: jnp.full(v.shape, NAN, v.dtype) for k, v in shapes.items()}
                return operand, jnp.full((), NAN), nan

            (carry, vstate), lam, metrics = jax.lax.cond(
                t % agent.cache_len == 0, do_plan, no_plan, (carry, vstate)
            )
        actor_params = s.actor.params if uses_actor else None
        a, carry = agent_lib.act(agent, actor_params, carry, k_act, training, t)
        if uses_actor and training:
            noise = c.explore.noise * agent_lib.explore_eps(carry, k_act, t)
            a = jnp.clip(a + noise, -1.0, 1.0)
            carry = carry.replace(prev_action=a)
        return a, s.replace(agent=carry, value=vstate), lam, metrics

    # Traced several times per program (output shapes, both branches of a lax.cond, FLOP counts);
    # as a jitted function with one identity the later traces come from JAX's cache. XLA inlines
    # it, so the compiled program is the same.
    policy = jax.jit(_policy, static_argnums=3)

    def act(s: TrainState, k_pol: jax.Array, k_rand: jax.Array, t: jax.Array, prefill: jax.Array):
        """Uniform random actions during the prefill (unbatched ``prefill``), else the policy."""
        shapes = jax.eval_shape(
            lambda st, k: policy(st, k, jnp.zeros((), jnp.int32), True), s, k_pol
        )

        def explore(s):
            a = jax.random.uniform(k_rand, (num_envs, action_dim), minval=-1.0, maxval=1.0)
            s = s.replace(agent=s.agent.replace(prev_action=a))
            nan = {k: jnp.full(v.shape, NAN, v.dtype) for k, v in shapes[3].items()}
            return a, s, jnp.full((), NAN), nan

        return jax.lax.cond(prefill, explore, lambda s: policy(s, k_pol, t, True), s)

    def step(s: TrainState, a: jax.Array) -> tuple[TrainState, jax.Array]:
        """The env step (action repeat inside) and the transition into the replay.
        -> (s, number of envs whose physics went non-finite)."""
        env_state = jax.vmap(env.step)(s.env, a)
        replay = replay_lib.add(
            s.replay,
            {
                "obs": env_state.obs,
                "action": a,
                "reward": env_state.reward,
                "is_first": jnp.zeros((num_envs,), bool),
            },
        )
        s = s.replace(env=env_state, replay=replay, ep_return=s.ep_return + env_state.reward)
        return s, jnp.sum(env_state.metrics["nan"])

    def end_episode(s: TrainState, key: jax.Array) -> TrainState:
        """Reset every env, store the first observations, forget the agent's episode state."""
        _, agent = bind(s.hyper)
        k_noise = None
        if agent_lib.carry_noise(s.agent) is not None:  # colored: the next episode's noise
            key, k_noise = jax.random.split(key)
        env_state = jax.vmap(env.reset)(jax.random.split(key, num_envs))
        return s.replace(
            env=env_state,
            replay=replay_lib.add(s.replay, first_row(env_state.obs)),
            agent=agent_lib.reset_carry(agent, s.agent, k_noise),
            ep_return=jnp.zeros_like(s.ep_return),
        )

    def prior_alone(c: Config) -> Config:
        """``c`` acting with its policy prior alone: the prior's rollout is the plan (no CEM, no
        collocation steps), replanned as often as the planner."""
        return c.model_copy(
            update={"planner": c.planner.model_copy(update={"iters": 0, "init": "policy"})}
        )

    task = env.unwrapped  # the task's own evaluation facts (Env.eval_signals / eval_metrics)

    def episodes(s: TrainState, agent, key: jax.Array):
        """``run.eval_episodes`` deterministic episodes of ``agent`` -> (env state, returns
        [episodes], episode 0's qpos [T, nq], the task's signals {name: [T + 1, episodes]})."""
        n = cfg.run.eval_episodes
        k_env, k_carry, key = jax.random.split(key, 3)
        env_state = jax.vmap(env.reset)(jax.random.split(k_env, n))
        vt = s.value.target if s.value is not None else None
        params = wm_lib.plan_params(s.wm, vt, s.actor.params if agent.uses_prior else None)
        carry = agent_lib.init_carry(agent, params, n, k_carry)
        actor_params = s.actor.params if uses_actor else None

        def one_step(carry_all, t):
            env_state, carry, ret = carry_all
            k = jax.random.fold_in(key, t)
            k_obs, k_plan, k_act = jax.random.split(k, 3)
            first = jnp.broadcast_to(t == 0, (n,))
            carry = agent_lib.observe(agent, s.wm, carry, env_state.obs, first, k_obs)
            if not uses_actor:
                carry = jax.lax.cond(
                    t % agent.cache_len == 0,
                    lambda cr: agent_lib.replan(agent, params, cr, k_plan)[0],
                    lambda cr: cr,
                    carry,
                )
            a, carry = agent_lib.act(agent, actor_params, carry, k_act, training=False)
            env_state = jax.vmap(env.step)(env_state, a)
            qpos = env_state.pipeline_state.qpos[0]
            return (env_state, carry, ret + env_state.reward), (
                qpos,
                task.eval_signals(env_state.pipeline_state),
            )

        first = task.eval_signals(env_state.pipeline_state)
        (env_state, _, returns), (qpos, signals) = jax.lax.scan(
            one_step, (env_state, carry, jnp.zeros((n,))), jnp.arange(episode_len)
        )
        signals = {k: jnp.concatenate([first[k][None], v]) for k, v in signals.items()}
        return env_state, returns, qpos, signals

    def evaluate(s: TrainState, key: jax.Array) -> dict[str, jax.Array]:
        """``run.eval_episodes`` deterministic episodes (no noise, clipped actions) with the current
        parameters; nothing is stored. Returns returns [episodes], episode 0's qpos [T, nq], the
        task's facts of these episodes (``task``: {name: scalar}, Env.eval_metrics; quadruped:
        starts on their feet, down starts that got up) and the reacher target of episode 0
        (``target_xy``, where the task has one).

        A run with a policy prior also acts with the prior alone on the same episodes (the same
        starts and keys): ``returns_prior`` [episodes], so every evaluation shows what the plan
        adds to its start (docs/EXPERIMENTS.md: at 100k on cheetah, nothing on average)."""
        c, agent = bind(s.hyper)
        env_state, returns, qpos, signals = episodes(s, agent, key)
        out = {"returns": returns, "qpos": qpos, "task": task.eval_metrics(signals, returns)}
        if "target_xy" in env_state.info:
            out["target_xy"] = env_state.info["target_xy"][0]
        if agent.uses_prior and (cfg.planner.iters > 0 or cfg.planner.init != "policy"):
            prior = agent_lib.make_agent(prior_alone(c), action_dim)
            out["returns_prior"] = episodes(s, prior, key)[1]
        return out

    return Rollout(
        start=start, act=act, step=step, end_episode=end_episode, evaluate=evaluate, policy=policy
    )

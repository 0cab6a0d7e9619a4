"""Every method trains: one chunk of each at debug sizes through the real trainer (reacher_easy,
the cheapest task to compile), with the world-model, value and actor updates it schedules.

Two seeds on one device: the programs are then those of the smoke study's cells and of the trainer
tests (same config, same shapes), which the persistent compile cache shares between them.

The value modes that learn from the plan (``plan_inner``, ``plan_final``), the augmented latent
objective J_latent, colored (pink) exploration noise and the disagreement bonus train here too, each with every float key
of the config swept (one value each, the config's own): what the paper's ablations run, and proof
that every key in ``config.float_keys`` traces. Every method's chunk, called for two consecutive chunks, is traced
and compiled once."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from mjx_collo import agent as agent_lib
from mjx_collo import config, parallel, trainer

METHODS = ["collodreamer", "latco", "dreamer", "cem", "mppi", "mppi_value"]


def _changed(a, b) -> bool:
    return any(
        not np.array_equal(np.asarray(x), np.asarray(y))
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True)
    )


def every_float_key(cfg) -> dict[str, list[float]]:
    """A sweep of every key in ``config.float_keys``, each at the config's own value."""
    flat = config.flatten(config.to_dict(cfg))
    return {k: [flat[k]] for k in config.float_keys(cfg)}


ABLATION_VARIANTS = {
    # debug plans run 3 solver iterations: a value step every one of them
    "plan_inner+j_latent": ["value.mode=plan_inner", "value.v_every=1", "j_latent.enabled=true"],
    # with colored (pink) exploration noise and Plan2Explore's disagreement bonus, one program
    # for all three: the noise is drawn per env and episode whatever the value mode, and
    # plan_final's value learns from the plans the bonus steers
    "plan_final+pink_explore+disag": [
        "value.mode=plan_final",
        "explore.color=1",
        "explore.disag.heads=3",
    ],
}


# cem and mppi (LatCo's shooting baselines, too costly per planning call for the studies) train in
# the slow suite: mppi_value runs the same shooting family through the trainer here, and
# tests/test_planner_shooting.py tests each planner. Keeps `make test` under its 15 minutes.
SLOW_METHODS = {"cem", "mppi"}


@pytest.mark.parametrize(
    "method, overrides",
    [pytest.param(m, [], marks=[pytest.mark.slow] if m in SLOW_METHODS else []) for m in METHODS]
    + [("collodreamer", v) for v in ABLATION_VARIANTS.values()]
    + [
        pytest.param("collodreamer", [f"planner.init={init}", *extra], marks=pytest.mark.slow)
        # the default plans from its prior (policy_cem); these are the prior alone with behaviour
        # cloning, and the planner alone from its CEM start (the paper preset's start)
        for init, extra in (("policy", ["actor.bc=1.0", "actor.starts=64"]), ("cem", []))
    ],
    ids=METHODS + list(ABLATION_VARIANTS) + ["policy_prior", "cem_start"],
)
def test_one_chunk_of_every_method_trains_and_evaluates(method, overrides):
    cfg = config.load(task="reacher_easy", method=method, presets=["debug"], overrides=overrides)
    tr = trainer.make_train(cfg, envs.from_config(cfg.env))
    traces = []

    def counted_chunk(s, it):
        traces.append(1)
        return tr.chunk(s, it)

    init, chunk, evaluate = parallel.batched(tr._replace(chunk=counted_chunk))
    sweep = every_float_key(cfg) if overrides else {}
    n, hyper, _ = parallel.sweep_grid(sweep, 2)
    keys = parallel.seed_keys(cfg, n)
    s0 = jax.device_get(init(keys, hyper))
    s_out, m = chunk(init(keys, hyper), jnp.zeros((), jnp.int32))
    s, m = jax.device_get((s_out, m))
    assert sorted(s.hyper) == sorted(sweep)

    # the chunk crossed the prefill and trained: pretraining plus scheduled updates
    run = cfg.run
    due = (run.chunk_env_steps - run.prefill) // run.train_every
    assert np.all(np.asarray(s.updates) == run.pretrain + run.train_steps * due)
    losses = np.asarray(m["wm/loss/total"])
    assert np.isfinite(losses).sum() > 0 and np.all(np.isfinite(losses) | np.isnan(losses))
    assert np.all(np.asarray(s.nonfinite_total) == 0)
    assert _changed(s.wm, s0.wm), "world-model parameters did not change"
    if cfg.value.enabled:
        assert _changed(s.value.params, s0.value.params), "value parameters did not change"
        loss = {"replay": "value/loss", "plan_final": "plan/plan_value/loss"}.get(
            cfg.value.mode, "plan/value/plan_loss"
        )  # plan_final: a value step per planning call; plan_inner: inside the planner
        assert np.isfinite(np.asarray(m[loss])).any(), sorted(m)
    if method == "dreamer" or cfg.planner.init.startswith("policy"):  # the policy prior's too
        assert _changed(s.actor.params, s0.actor.params), "actor parameters did not change"
    if method != "dreamer":
        plan_returns = np.asarray(m["plan/plan_return"])
        assert np.isfinite(plan_returns).any(), "no planning call after the prefill"
    if cfg.j_latent.enabled:
        jl = np.asarray(m["wm/loss/j_latent"])
        assert np.isfinite(jl).any() and np.all(np.isfinite(jl) | np.isnan(jl)), sorted(m)

    if cfg.explore.color > 0:  # one noise sequence per env and episode, redrawn at each reset
        steps = cfg.env.episode_env_steps // cfg.env.action_repeat
        assert agent_lib.carry_noise(s.agent).shape[-2:] == (steps, s.agent.prev_action.shape[-1])
        assert run.chunk_env_steps > cfg.env.episode_env_steps  # the chunk crossed episode ends
        assert _changed(agent_lib.carry_noise(s.agent), agent_lib.carry_noise(s0.agent))

    if cfg.explore.disag.heads:  # the ensemble learns beside the world model
        assert _changed(s.explorer.params, s0.explorer.params), "ensemble did not change"
        disag = np.asarray(m["explore/disag"])  # NaN in the iterations without updates
        trained = np.isfinite(disag)
        assert trained.any() and np.all(disag[trained] > 0) and np.all(trained | np.isnan(disag))

    if overrides:
        # the ablation modes act and evaluate as collodreamer does (the value learns only in
        # training): their evaluation is the default's, compiled in the collodreamer case
        return
    # The chunk called again, for the next chunk, is not traced again, hence not recompiled: the
    # state it returns has exactly the shapes, dtypes and structure it took (a weak-typed or
    # re-shaped leaf would retrace and recompile every chunk), and the schedule position is an
    # array, not a Python int baked into the program.
    s2, _ = chunk(s_out, jnp.asarray(tr.iterations_per_chunk, jnp.int32))
    assert len(traces) == 1
    assert np.all(np.asarray(jax.device_get(s2.updates)) > np.asarray(s.updates))

    out = jax.device_get(evaluate(s, keys))
    returns = np.asarray(out["returns"])
    assert returns.shape == (2, cfg.run.eval_episodes) and np.all(np.isfinite(returns))
    assert np.all(returns <= cfg.env.episode_env_steps)

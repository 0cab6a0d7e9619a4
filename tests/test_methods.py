"""Every method trains: one chunk of each at debug sizes through the real trainer (reacher_easy,
the cheapest task to compile), with the world-model, value and actor updates it schedules.

Two seeds on one device: the programs are then those of the smoke study's cells and of the trainer
tests (same config, same shapes), which the persistent compile cache shares between them."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from mjx_collo import config, parallel, trainer

METHODS = ["collodreamer", "latco", "dreamer", "cem", "mppi", "mppi_value"]


def _changed(a, b) -> bool:
    return any(
        not np.array_equal(np.asarray(x), np.asarray(y))
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True)
    )


@pytest.mark.parametrize("method", METHODS)
def test_one_chunk_of_every_method_trains_and_evaluates(method):
    cfg = config.load(task="reacher_easy", method=method, presets=["debug"])
    tr = trainer.make_train(cfg, envs.from_config(cfg.env))
    init, chunk, evaluate = parallel.batched(tr)
    keys = parallel.seed_keys(cfg, 2)
    s0 = jax.device_get(init(keys, {}))
    s, m = chunk(init(keys, {}), jnp.zeros((), jnp.int32))
    s, m = jax.device_get((s, m))

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
        assert np.isfinite(np.asarray(m["value/loss"])).any()
    if method == "dreamer":
        assert _changed(s.actor.params, s0.actor.params), "actor parameters did not change"
    else:
        plan_returns = np.asarray(m["plan/plan_return"])
        assert np.isfinite(plan_returns).any(), "no planning call after the prefill"

    out = jax.device_get(evaluate(s, keys))
    returns = np.asarray(out["returns"])
    assert returns.shape == (2, cfg.run.eval_episodes) and np.all(np.isfinite(returns))
    assert np.all(returns <= cfg.env.episode_env_steps)

"""Every key in ``config.float_keys`` can be swept within one compile, on every code path that
reads it: the chunk of each method (and of the collocation solvers and the value modes that read
keys the default does not) traces with every float key swept at once. Tracing is where a swept
value fails (a Python ``if`` on it: TracerBoolConversionError), so this needs no compile; the
default method and the ablation variants also run a chunk swept (``test_methods.py``)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import pytest

import envs
from mjx_collo import config, parallel, trainer

# method, overrides, keys left out (with why)
PATHS = {
    "dreamer": ("dreamer", [], {}),
    "latco": ("latco", [], {}),
    "cem": ("cem", [], {}),
    "mppi_value": ("mppi_value", [], {}),
    "collodreamer": ("collodreamer", [], {}),  # the default: plans from its policy prior
    "cem_start": ("collodreamer", ["planner.init=cem"], {}),  # the planner alone (paper preset)
    "gauss_newton+refine": (
        "collodreamer",
        ["planner.solver=gauss_newton", "planner.refine_iters=2", "planner.value_lambda=1.0"],
        # a swept lambda is a lambda-return over the plan, which the Gauss-Newton residuals
        # cannot express (config validation says so for a fixed lambda < 1 too)
        {"planner.value_lambda"},
    ),
}


@pytest.mark.parametrize("path", list(PATHS))
def test_every_float_key_sweeps_in_one_trace(path):
    method, overrides, left_out = PATHS[path]
    cfg = config.load(task="reacher_easy", method=method, presets=["debug"], overrides=overrides)
    flat = config.flatten(config.to_dict(cfg))
    sweep = {k: [flat[k]] for k in config.float_keys(cfg) if k not in left_out}
    assert len(sweep) >= 50
    n, hyper, _ = parallel.sweep_grid(sweep, 1)  # one run whose hyper holds every key
    tr = trainer.make_train(cfg, envs.from_config(cfg.env))
    init, chunk, _ = parallel.batched(tr)
    state = jax.eval_shape(init, parallel.seed_keys(cfg, n), hyper)
    out, metrics = jax.eval_shape(chunk, state, jax.ShapeDtypeStruct((), jnp.int32))
    assert sorted(out.hyper) == sorted(sweep)
    assert "wm/loss/total" in metrics


def test_a_sweep_a_path_cannot_take_is_refused_with_one_line():
    cfg = config.load(
        task="reacher_easy",
        presets=["debug"],
        overrides=["planner.solver=gauss_newton", "planner.value_lambda=1.0"],
    )
    with pytest.raises(config.ConfigError, match="planner.solver=adam"):
        config.parse_sweep("planner.value_lambda=0.8,1.0", cfg)
    # a float that decides what the acting state holds (the episode's colored noise, or none)
    assert "explore.color" not in config.float_keys(cfg)
    with pytest.raises(config.ConfigError, match="'explore.color'.*one value per run"):
        config.parse_sweep("explore.color=0,1", cfg)


def test_plan_inner_that_would_never_step_the_value_is_refused():
    """value.mode=plan_inner steps the value every value.v_every solver iterations: with fewer
    iterations per planning call the value silently never learned (found by the plan_inner
    chunk in test_methods.py, at debug sizes: 3 iterations, v_every 10)."""
    cfg = config.load(task="reacher_easy", presets=["debug"], overrides=["value.mode=plan_inner"])
    with pytest.raises(config.ConfigError, match=r"value.v_every <= 3"):
        trainer.validate(cfg)
    trainer.validate(cfg.model_copy(update={"value": cfg.value.model_copy(update={"v_every": 3})}))


def test_tied_keys_take_their_values_together():
    """``a+b=v1,v2`` is one axis of the grid (the paper's discount ablation varies the value's
    and the planner's discount as one), crossed with the other items and the seeds."""
    cfg = config.load(task="reacher_easy", presets=["debug"])
    sweep = config.parse_sweep("value.gamma+planner.gamma=0.9,0.99 wm.optim.lr=1e-3,2e-3", cfg)
    n, hyper, labels = parallel.sweep_grid(sweep, 2)
    assert n == 8 and sorted(hyper) == ["planner.gamma", "value.gamma", "wm.optim.lr"]
    assert [lab["value.gamma"] for lab in labels] == [lab["planner.gamma"] for lab in labels]
    assert sorted({(lab["value.gamma"], lab["wm.optim.lr"]) for lab in labels}) == [
        (0.9, 1e-3),
        (0.9, 2e-3),
        (0.99, 1e-3),
        (0.99, 2e-3),
    ]
    with pytest.raises(config.ConfigError, match="repeats a key"):
        config.parse_sweep("value.gamma+planner.gamma=0.9 value.gamma=0.95", cfg)
    with pytest.raises(config.ConfigError, match="cannot sweep 'planner.horizon'"):
        config.parse_sweep("value.gamma+planner.horizon=0.9", cfg)


def test_seeds_trained_alone_have_the_keys_of_one_vmapped_run():
    """``train.py --seeds 1 --first-seed 2`` trains seed 2 of ``--seeds 3``: the same key and
    label, so a study can train a cell's seeds one program at a time; evaluation and the probe
    find the key again from the labels. A sweep's seeds train together."""
    cfg = config.load(task="reacher_easy", presets=["debug"])
    together = parallel.seed_keys(cfg, 3)
    alone = parallel.seed_keys(cfg, 1, first=2)
    assert (alone[0] == together[2]).all() and not (alone[0] == together[0]).all()
    n, _, labels = parallel.sweep_grid({}, 2, first=1)
    assert n == 2 and labels == [{"seed": 1}, {"seed": 2}]
    assert parallel.first_seed(labels) == 1
    assert parallel.first_seed([{"seed": 1, "value.gamma": 0.9}]) == 0  # a sweep: run index
    with pytest.raises(config.ConfigError, match="--first-seed"):
        parallel.sweep_grid({"value.gamma": [0.9, 0.99]}, 1, first=1)

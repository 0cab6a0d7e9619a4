"""End to end: the debug preset trains 2 seeds for 2 chunks; save, restore, continue equals the
uninterrupted run bit for bit; the chunk compiles once; seeds differ; bad inputs fail with one line.

Uses the real reacher task (the cheapest MJX program to compile) and the real world model and
planner at debug sizes.
"""

from __future__ import annotations

import functools
import json
import shutil
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

import envs
from mjx_collo import config, metrics, parallel, runner, trainer
from mjx_collo import flops as flops_lib

TASK = "reacher_easy"


def debug_cfg(method: str = "collodreamer", overrides=()) -> config.Config:
    return config.load(task=TASK, method=method, presets=["debug"], overrides=list(overrides))


def make_env(cfg: config.Config):
    return envs.from_config(cfg.env)


@functools.cache
def uninterrupted_and_resumed(tmp_root: str):
    """Run A: 2 chunks in one go, checkpointing after each. Run B resumes from A's first
    checkpoint and runs the 2nd chunk."""
    cfg = debug_cfg()
    env = make_env(cfg)
    total = 2 * cfg.run.chunk_env_steps
    run_a = runner.Run(cfg, env, f"{tmp_root}/a", num_seeds=2, progress=False, log=lambda *_: None)
    res_a = run_a.run(total)
    state_a = jax.device_get(run_a.state)
    run_a.close()

    # Run B: a new Run object (as after a restart) on a copy of A's directory that holds only the
    # checkpoint A wrote after its first chunk, as if A had been killed right after writing it.
    shutil.copytree(f"{tmp_root}/a", f"{tmp_root}/b")
    shutil.rmtree(f"{tmp_root}/b/checkpoints/{total}")
    run_b = runner.Run(cfg, env, f"{tmp_root}/b", num_seeds=2, progress=False, log=lambda *_: None)
    res_b = run_b.run(total)
    state_b = jax.device_get(run_b.state)
    run_b.close()
    return cfg, (res_a, state_a), (res_b, state_b)


# Session scope: the xdist worker that runs these tests trains runs A and B once. Every test that
# reads them is in one xdist group (`--dist loadgroup` in `make test`), so one worker trains
# them, not each; a group starts first (tests/conftest.py), so it is not the suite's tail.
ON_RUNS = pytest.mark.xdist_group("trainer_runs")


@pytest.fixture(scope="session")
def runs(tmp_path_factory):
    return uninterrupted_and_resumed(str(tmp_path_factory.mktemp("runs")))


@ON_RUNS
def test_resumed_run_equals_uninterrupted_bit_for_bit(runs):
    cfg, (res_a, state_a), (res_b, state_b) = runs
    assert res_a.env_steps == res_b.env_steps == 2 * cfg.run.chunk_env_steps
    assert (
        len(res_b.chunk_s) == 1
    )  # B resumed at the first checkpoint and ran only the second chunk
    leaves_a, tree_a = jax.tree.flatten(state_a)
    leaves_b, tree_b = jax.tree.flatten(state_b)
    assert tree_a == tree_b
    for i, (a, b) in enumerate(zip(leaves_a, leaves_b, strict=True)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=f"leaf {i}")
    # training happened: world-model updates were applied and the replay holds data
    assert int(np.min(state_a.updates)) > 0
    # eval returns at the end agree too
    np.testing.assert_array_equal(res_a.eval_returns[-1][1], res_b.eval_returns[-1][1])


@ON_RUNS
def test_run_directory_has_config_metrics_plots_checkpoints(runs, tmp_path_factory):
    cfg, (res_a, _), _ = runs
    d = res_a.run_dir
    assert (d / "config.yaml").exists()
    rows = [json.loads(x) for x in (d / "metrics.jsonl").read_text().splitlines()]
    kinds = {r["kind"] for r in rows}
    assert kinds == {"train", "eval"}
    assert any("wm/loss/total" in r for r in rows) and any("eval/return" in r for r in rows)
    assert {r["seed"] for r in rows} == {0, 1}
    for name in ("returns.png", "world_model.png", "violations.png"):
        assert (d / "plots" / name).stat().st_size > 1000
    # every panel a plot promises is a metric the run writes (a renamed key would drop it silently)
    written = set().union(*rows)
    for name, (_, keys) in metrics.PLOTS.items():
        # actor/*: dreamer (and the prior) only; eval/return_prior: policy-prior runs only (see
        # test_make_eval_acts_with_the_prior_alone_or_the_planner_alone)
        missing = {k for k in keys if not k.startswith("actor/")} - written - {"eval/return_prior"}
        assert not missing, (name, missing)
    assert any((d / "tb" / "seed0").iterdir())
    steps = sorted(int(p.name) for p in (d / "checkpoints").iterdir() if p.name.isdigit())
    assert steps[-1] == 2 * cfg.run.chunk_env_steps


@ON_RUNS
def test_metrics_carry_wall_time_that_a_resumed_run_continues(runs):
    """Each row says how long the run had been going (``perf/wall_s``, launches and compiles
    included), evaluations how long they took: speed comparisons read them off metrics.jsonl.
    Run B resumed from A's first checkpoint; its clock continues from A's rows, not from 0."""
    cfg, (res_a, _), (res_b, _) = runs

    def rows(res):
        lines = (res.run_dir / "metrics.jsonl").read_text().splitlines()
        return [json.loads(x) for x in lines]

    a, b = rows(res_a), rows(res_b)
    walls = [r["perf/wall_s"] for r in a if r["seed"] == 0]
    assert len(walls) == len(a) // 2 and walls == sorted(walls) and walls[0] > 0
    assert all(r["perf/eval_s"] > 0 for r in a if r["kind"] == "eval")
    first = cfg.run.chunk_env_steps
    a_at_first = max(r["perf/wall_s"] for r in a if r["step"] == first)
    b_last = max(r["perf/wall_s"] for r in b if r["step"] == 2 * first)
    assert b_last >= a_at_first + res_b.chunk_s[0]


@ON_RUNS
def test_the_replay_holds_exactly_the_rows_the_run_writes(runs):
    """Sized to the run (a 100k pixel run: 0.6 GiB per seed, not the 2.9 GiB of a 500k
    capacity), and nothing written is ever overwritten: full at the end, the first row intact."""
    from mjx_collo import rollout

    cfg, (_, state), _ = runs
    rows = rollout.run_replay_rows(cfg)
    assert rows < cfg.replay.capacity // cfg.env.action_repeat // cfg.run.num_envs
    assert np.asarray(state.replay.data["is_first"]).shape[1] == rows
    np.testing.assert_array_equal(np.asarray(state.replay.count), [rows, rows])
    assert np.asarray(state.replay.data["is_first"])[:, 0].all()


# the old, capacity-sized format in make test-all only: make test stays under its 15 minutes
@pytest.mark.parametrize(
    "first_buffer",
    ["sized_to_a_shorter_run", pytest.param("capacity_sized_old_format", marks=pytest.mark.slow)],
)
@ON_RUNS
def test_an_extended_or_old_checkpoint_resumes_bit_for_bit(
    runs, tmp_path, monkeypatch, first_buffer
):
    """Run A's first chunk saved by a run of one chunk (its replay sized to that chunk), or by the
    code before replays were sized to the run (capacity-sized, no row count in the checkpoint);
    resumed for A's whole length, the buffer is moved to A's size and the result is A's, bit for
    bit."""
    import yaml

    from mjx_collo import rollout

    cfg, (res_a, state_a), _ = runs
    chunk = cfg.run.chunk_env_steps
    quiet = dict(num_seeds=2, progress=False, log=lambda *_: None)
    short = debug_cfg(overrides=[f"run.steps={chunk}"])
    with monkeypatch.context() as m:
        if first_buffer == "capacity_sized_old_format":
            m.setattr(rollout, "run_replay_rows", lambda cfg: 10**9)
        first = runner.Run(short, make_env(short), tmp_path / "r", **quiet)
        first.run()
        rows_first = np.asarray(first.state.replay.data["is_first"]).shape[1]
        first.close()
    if first_buffer == "capacity_sized_old_format":
        assert rows_first == cfg.replay.capacity // cfg.env.action_repeat // cfg.run.num_envs
        meta_file = tmp_path / "r" / "checkpoints" / str(chunk) / "meta" / "metadata"
        meta = json.loads(meta_file.read_text())
        del meta["replay_rows"]
        meta_file.write_text(json.dumps(meta))
    else:
        assert rows_first == rollout.run_replay_rows(short)
    again = runner.Run(cfg, make_env(cfg), tmp_path / "r", **quiet)
    res = again.run()
    state = jax.device_get(again.state)
    again.close()
    assert len(res.chunk_s) == 1
    # `make train STEPS=...` again on a shorter finished run trains on; config.yaml then says how
    # long the run is now, not how long it was first asked to be.
    saved = yaml.safe_load((tmp_path / "r" / "config.yaml").read_text())
    assert saved["run"]["steps"] == cfg.run.steps == 2 * chunk
    leaves_a, tree_a = jax.tree.flatten(state_a)
    leaves, tree = jax.tree.flatten(state)
    assert tree == tree_a
    for i, (a, b) in enumerate(zip(leaves_a, leaves, strict=True)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=f"leaf {i}")
    np.testing.assert_array_equal(res_a.eval_returns[-1][1], res.eval_returns[-1][1])


@ON_RUNS
def test_seeds_differ_in_init_and_data(runs):
    _, (_, state), _ = runs
    w = jax.tree.leaves(state.wm)
    assert any(not np.allclose(np.asarray(x)[0], np.asarray(x)[1]) for x in w)
    obs = np.asarray(state.replay.data["obs"])
    assert not np.allclose(obs[0], obs[1])


ROOT = Path(__file__).resolve().parent.parent


def _cli(script: str, argv: list[str]) -> subprocess.CompletedProcess:
    """Run ``train.py`` / ``evaluate.py`` as a user does (a fresh process, the test suite's
    compile cache and flags, conftest.py)."""
    return subprocess.run(
        [sys.executable, str(ROOT / script), *argv],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=600,
    )


def _main_error(argv, script: str = "train.py") -> str:
    proc = _cli(script, argv)
    err = proc.stderr.strip()
    assert proc.returncode == 2, (proc.stdout, err)
    assert len(err.splitlines()) == 1, err
    return err


def test_bad_env_fails_with_one_line(tmp_path):
    err = _main_error(["--env", "cheeta", "--run", str(tmp_path)])
    assert "unknown task 'cheeta'" in err and "cheetah_run" in err


def test_bad_override_key_fails_with_one_line(tmp_path):
    err = _main_error(["--env", "reacher", "--run", str(tmp_path), "wm.detr=3"])
    assert "wm.detr" in err and "deter" in err


def test_wrong_type_fails_with_one_line(tmp_path):
    err = _main_error(["--env", "reacher", "--run", str(tmp_path), "wm.deter=abc"])
    assert "wm.deter" in err and "integer" in err


def test_bad_sweep_fails_with_one_line(tmp_path):
    err = _main_error(["--env", "reacher", "--run", str(tmp_path), "--sweep", "wm.deter=100,200"])
    assert "wm.deter" in err and "float" in err


def test_first_seed_with_a_sweep_fails_with_one_line(tmp_path):
    err = _main_error(
        ["--env", "reacher", "--run", str(tmp_path), "--first-seed", "2"]
        + ["--sweep", "value.gamma=0.9,0.99"]
    )
    assert "--first-seed 2" in err and "sweep" in err


@ON_RUNS
def test_other_seeds_on_a_run_directory_fail_with_one_line(runs):
    """Seeds 1-2 asked of a run directory that holds seeds 0-1 (a study part resumed with
    another --first-seed): refused before compiling, naming both."""
    _, (res_a, _), _ = runs
    err = _main_error(
        ["--env", TASK, "--preset", "debug", "--seeds", "2", "--first-seed", "1"]
        + ["--run", str(res_a.run_dir)]
    )
    assert "{'seed': 0}, {'seed': 1}" in err and "{'seed': 1}, {'seed': 2}" in err


@ON_RUNS
def test_checkpoint_from_another_config_fails_with_one_line(runs):
    _, (res_a, _), _ = runs
    err = _main_error(
        [
            "--env",
            TASK,
            "--preset",
            "debug",
            "--seeds",
            "2",
            "--run",
            str(res_a.run_dir),
            "wm.deter=32",
        ],
    )
    assert "different config" in err and "wm.deter: 16 -> 32" in err


@pytest.mark.parametrize(
    "override, message",
    [
        ("wm.deter=32", "cannot override 'wm.deter'"),
        ("planner.kind=dreamer", "only dreamer checkpoints hold an actor"),
        ("planner.mpc_step=4", "unknown config key 'planner.mpc_step'"),
    ],
)
@ON_RUNS
def test_make_eval_rejects_overrides_that_do_not_fit_the_checkpoint(runs, override, message):
    _, (res_a, _), _ = runs
    err = _main_error(["--ckpt", str(res_a.run_dir), override], "evaluate.py")
    assert message in err, err


def test_a_checkpoint_without_a_prior_cannot_be_evaluated_with_one():
    """`make eval ... planner.init=policy` on a run that trained no prior (the paper preset, or
    planner.init=cem) is one line naming why; the reverse (a prior run's planner alone) is taken."""
    from mjx_collo import session

    no_prior = debug_cfg(overrides=["planner.init=cem"])
    with pytest.raises(config.ConfigError, match="planner.init=cem and holds no policy prior"):
        session.eval_config(no_prior, ["planner.init=policy"])
    assert session.eval_config(debug_cfg(), ["planner.init=cem"]).planner.init == "cem"


@ON_RUNS
def test_make_eval_acts_with_the_prior_alone_or_the_planner_alone(runs, tmp_path):
    """A checkpoint of the default, which trains the policy prior (planner.init=policy_cem), is
    evaluated three ways on the same episodes, as docs/ALGORITHM.md §4.10 tells users to: with
    both (here with another planner budget, mpc_steps 2 -> 4, which changes the shape of the
    acting caches saved in the checkpoint), with the prior alone (its rollout is the plan:
    planner.iters=0 planner.init=policy) and with the planner alone (planner.init=cem, whose
    config has no prior to train: the prior's training keys must not refuse it). Each writes a
    per-seed table and eval_<step>.json recording its overrides. A planner that cannot start
    from the prior is one line naming the fix."""
    cfg, (res_a, _), _ = runs  # the default ColloDreamer trains its prior (policy_cem)
    assert cfg.planner.init == "policy_cem" and cfg.planner.mpc_steps == 2
    run = res_a.run_dir
    results = {}
    budget = ["planner.mpc_steps=4"]
    for name, overrides in {
        "both": budget + ["planner.iters=5"],
        "prior": budget + ["planner.iters=0", "planner.init=policy"],
        "planner": ["planner.init=cem"],
    }.items():
        out = tmp_path / name
        proc = _cli(
            "evaluate.py", ["--ckpt", str(run), "--episodes", "2", "--out", str(out)] + overrides
        )
        assert proc.returncode == 0, (proc.stdout, proc.stderr)
        results[name] = json.loads((out / "eval_800.json").read_text())  # named by the step
        assert results[name]["overrides"] == overrides
        assert results[name]["env_steps"] == 800 and len(results[name]["runs"]) == 2
        returns = np.array([r["returns"] for r in results[name]["runs"]])
        assert returns.shape == (2, 2) and np.all(np.isfinite(returns))
        # dm_control rewards lie in [0, 1] per env step: a return is at most the episode's length
        assert np.all(returns <= cfg.env.episode_env_steps)
        assert "seed=0" in proc.stdout and "seed=1" in proc.stdout and "all runs" in proc.stdout
    # the episodes acted with the override (the saved caches were shaped for mpc_steps=2)
    assert results["both"]["planner"]["mpc_steps"] == 4 and results["both"]["planner"]["iters"] == 5
    # every evaluation of a prior run also acts with the prior alone on the same episodes: in
    # training (metrics.jsonl) and in make eval, where it matches the prior-alone evaluation
    rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    evals = [r for r in rows if r["kind"] == "eval"]
    assert evals and all(np.isfinite(r["eval/return_prior"]) for r in evals)
    both, prior = results["both"], results["prior"]
    np.testing.assert_allclose(
        both["prior_mean_over_runs"], prior["mean_over_runs"], rtol=1e-3, atol=1e-3
    )
    assert "prior_mean_over_runs" not in prior  # acting with the prior already
    assert results["prior"]["planner"]["init"] == "policy"
    assert results["prior"]["planner"]["iters"] == 0
    assert results["planner"]["planner"]["init"] == "cem"
    err = _main_error(["--ckpt", str(run), "planner.kind=mppi_value"], "evaluate.py")
    assert "planner.init=cem" in err, err


def test_config_inconsistency_names_the_fix():
    with pytest.raises(config.ConfigError, match="multiple of run.chunk_env_steps"):
        trainer.validate(debug_cfg(overrides=["run.eval_every=500"]))
    with pytest.raises(config.ConfigError, match="add planner.value_lambda=1.0"):
        trainer.validate(debug_cfg(overrides=["planner.solver=gauss_newton"]))
    trainer.validate(debug_cfg(overrides=["planner.solver=gauss_newton", "planner.value_lambda=1"]))
    env = envs.from_config(debug_cfg().env)
    with pytest.raises(config.ConfigError, match="has no collocation plan"):
        trainer.make_train(debug_cfg("cem", overrides=["planner.init=policy"]), env)
    with pytest.raises(config.ConfigError, match="needs value.enabled=true"):
        trainer.make_train(debug_cfg(overrides=["planner.init=policy", "value.enabled=false"]), env)
    with pytest.raises(config.ConfigError, match="set planner.init=policy or policy_cem"):
        trainer.make_train(debug_cfg(overrides=["planner.init=cem", "actor.bc=1.0"]), env)  # inert
    # the default's imagination starts are inert when a user plans without the prior
    assert not config.uses_prior(debug_cfg(overrides=["planner.init=cem", "actor.starts=64"]))
    trainer.make_train(debug_cfg(overrides=["planner.init=cem"]), env)  # runs as the planner alone
    with pytest.raises(config.ConfigError, match="must be >= 0"):
        trainer.make_train(debug_cfg(overrides=["planner.init=policy", "actor.starts=-1"]), env)
    with pytest.raises(config.ConfigError, match="cannot sweep 'actor.bc'"):
        config.parse_sweep("actor.bc=0,1", debug_cfg(overrides=["planner.init=cem"]))
    assert "actor.bc" in config.float_keys(debug_cfg())  # the default trains a prior


def test_task_overlay_sits_between_the_method_and_the_users_overrides():
    """configs/task/<task>.yaml changes only what it names, for that task, and an override wins."""
    quadruped = config.load(task="quadruped_walk")
    cheetah = config.load(task="cheetah_run")
    assert (quadruped.env.physics, cheetah.env.physics) == ("tuned", "dmc")
    assert quadruped.env.action_repeat == cheetah.env.action_repeat
    assert config.load(task="quadruped_walk", method="latco").env.physics == "tuned"
    mine = config.load(task="quadruped_walk", overrides=["env.physics=dmc"])
    assert mine.env.physics == "dmc"
    for name in config.available_presets("task"):
        config.load(task=name)  # every overlay names real keys with the right types


def test_the_default_collodreamer_is_one_config_for_every_task():
    """One set of defaults for every task (issue 39): the default ColloDreamer plans from its
    policy prior on cheetah, reacher and quadruped alike; the only task overlay is quadruped's
    physics options, and `--preset paper` keeps the paper's agent, which has no prior."""
    tasks = ("cheetah_run", "reacher_easy", "quadruped_walk")
    agents = {t: config.to_dict(config.load(task=t, method="collodreamer")) for t in tasks}
    for t in tasks:
        agents[t]["env"].pop("task"), agents[t]["env"].pop("physics")
    assert agents["cheetah_run"] == agents["reacher_easy"] == agents["quadruped_walk"]
    cfg = config.load(task="reacher_easy", method="collodreamer")
    assert config.uses_prior(cfg) and cfg.planner.init == "policy_cem"
    assert (cfg.wm.reward_head, cfg.wm.loss_scales.reward) == ("twohot", 10.0)
    paper = config.load(task="reacher_easy", method="collodreamer", presets=["paper"])
    assert not config.uses_prior(paper) and paper.planner.iters == 50
    assert (paper.wm.reward_head, paper.run.train_steps, paper.replay.batch) == ("mse", 100, 16)
    # the baselines keep their own settings: the default's prior and reward head are its own
    latco = config.load(task="reacher_easy", method="latco")
    assert (latco.wm.reward_head, latco.run.train_steps, latco.planner.init) == ("mse", 100, "cem")
    # without a prior its training keys are inert: a planner-alone run (planner.init=cem) resumes
    # and combines with one written before the default set actor.starts
    alone = config.load(task="reacher_easy", overrides=["planner.init=cem"])
    older = config.load(task="reacher_easy", overrides=["planner.init=cem", "actor.starts=0"])
    assert config.diff(alone, older) == []
    assert config.diff(cfg, config.load(task="reacher_easy", overrides=["actor.starts=0"]))


def test_one_seed_runs_unbatched_and_matches_the_vmapped_program():
    """A seed axis of size 1 is dropped (batched dots are slow on XLA's CPU backend): same
    numbers as the vmapped program, no batch dimension in any dot, the axis back on the output."""
    import jax.numpy as jnp

    def f(w, x, scale):
        return {"y": jnp.tanh(x @ w) * scale, "n": jnp.sum(w)}

    g = parallel.over_seeds(f, (0, 0, None))
    key_w, key_x = jax.random.split(jax.random.PRNGKey(0))
    for seeds in (1, 3):
        w = jax.random.normal(key_w, (seeds, 8, 4))
        x = jax.random.normal(key_x, (seeds, 5, 8))
        got = jax.jit(g)(w, x, 2.0)
        want = jax.vmap(f, in_axes=(0, 0, None))(w, x, 2.0)
        assert got["y"].shape == (seeds, 5, 4) and got["n"].shape == (seeds,)
        np.testing.assert_allclose(got["y"], want["y"], rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(got["n"], want["n"], rtol=1e-6)
        dots = [
            e.params["dimension_numbers"]
            for e in jax.make_jaxpr(g)(w, x, 2.0).jaxpr.eqns
            if e.primitive.name == "dot_general"
        ]
        batch_dims = [d[1] for d in dots]
        assert all(b == ((), ()) for b in batch_dims) == (seeds == 1), batch_dims


def test_incomplete_distributed_arguments_fail_with_one_line():
    err = _main_error(["--env", "reacher", "--distributed", "--coordinator", "h:1234"])
    assert "--num-processes" in err and "--process-id" in err


def test_matmul_budget_follows_the_schedule_and_the_planner_settings():
    """The FLOPs the run prints at start: a steady chunk is its planning calls and updates, and
    a dearer planner setting shows in the planning call only."""

    def costs(*overrides):
        cfg = debug_cfg(overrides=overrides)
        tr = trainer.make_train(cfg, make_env(cfg))
        c = tr.costs(jax.eval_shape(tr.init, jax.random.PRNGKey(0), {}))
        return cfg, tr, c

    cfg, tr, c = costs()
    run = cfg.run
    b = flops_lib.matmul_budget(tr, c)
    assert c["act"].flops > 0 and c["update"].flops > 0
    calls = tr.iterations_per_chunk / tr.plan_every
    updates = run.chunk_env_steps / run.train_every * run.train_steps
    assert b["chunk_gflop"] == pytest.approx(calls * c["act"].gflops + updates * c["update"].gflops)
    assert b["plan_call_gflop_per_env"] == pytest.approx(c["act"].gflops / run.num_envs)
    _, _, c2 = costs(f"planner.iters={2 * cfg.planner.iters}")
    assert c2["act"].flops > c["act"].flops
    assert c2["update"].flops == c["update"].flops

"""Studies: the config is checked before anything trains, a changed study is refused, and the
smoke study (2 variants x 1 task x 2 seeds) runs, resumes without retraining finished cells, and
reports."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from mjx_collo import config, report, study

ROOT = Path(__file__).resolve().parent.parent
SMOKE = ROOT / "configs" / "study" / "smoke.yaml"


def _study_yaml(tmp_path: Path, **changes) -> Path:
    raw = yaml.safe_load(SMOKE.read_text())
    raw.update(changes)
    path = tmp_path / "s.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"tasks": ["cheeta"]}, "unknown task 'cheeta'"),
        ({"variants": [{"name": "x", "method": "colodreamer"}]}, "colodreamer"),
        ({"overrides": ["wm.detr=3"]}, "wm.detr"),
        ({"variants": [{"name": "a b", "method": "latco"}]}, "variant name"),
        ({"variants": [{"name": "p", "method": "latco", "budget": "paper"}]}, "paper_budgets"),
        ({"seeds": 0}, "seeds"),
    ],
)
def test_bad_study_config_fails_with_one_line_before_training(tmp_path, changes, message):
    with pytest.raises(study.StudyError, match=message) as e:
        study.load(str(_study_yaml(tmp_path, **changes)))
    assert "\n" not in str(e.value)


def test_a_key_given_twice_in_a_study_or_an_overlay_is_refused_naming_both_lines(tmp_path):
    """YAML would keep the second silently: a second `variants:` or `planner:` block would drop
    what the first one set."""
    path = tmp_path / "twice.yaml"
    path.write_text(SMOKE.read_text() + "\nseeds: 5\n")
    with pytest.raises(study.StudyError, match=r"key 'seeds' appears twice .*lines \d+ and \d+"):
        study.load(str(path))
    overlay = tmp_path / "overlay.yaml"
    overlay.write_text("planner: {iters: 3}\nwm: {deter: 8}\nplanner: {horizon: 5}\n")
    with pytest.raises(config.ConfigError, match=r"key 'planner' appears twice .*lines 1 and 3"):
        config.read_yaml(overlay)
    overlay.write_text("planner: {iters: [3}\n")
    with pytest.raises(config.ConfigError, match="not valid YAML"):
        config.read_yaml(overlay)
    # a merge key is no repetition: the keys beside it override the merged ones
    overlay.write_text("a: &x {iters: 3, horizon: 5}\nb:\n  <<: *x\n  horizon: 7\n")
    assert config.read_yaml(overlay)["b"] == {"iters": 3, "horizon": 7}


def test_every_committed_study_config_resolves():
    for path in sorted((ROOT / "configs" / "study").glob("*.yaml")):
        _, cfg = study.load(str(path))
        assert study.cells(cfg)


def test_a_study_started_with_another_config_is_refused_naming_the_keys(tmp_path):
    _, cfg = study.load(str(SMOKE))
    study.pin_config(tmp_path, cfg)
    study.pin_config(tmp_path, cfg)  # the same config resumes
    changed = cfg.model_copy(update={"seeds": 3, "steps": 1200})
    with pytest.raises(study.StudyError, match=r"seeds: 2 -> 3; steps: 800 -> 1200"):
        study.pin_config(tmp_path, changed)
    # a new footnote changes no cell: taken, and stored for the next comparison
    noted = cfg.model_copy(update={"notes": [*cfg.notes, "a cell was rerun"]})
    study.pin_config(tmp_path, noted)
    assert "a cell was rerun" in (tmp_path / "study.yaml").read_text()
    with pytest.raises(study.StudyError, match=r"seeds: 2 -> 3"):
        study.pin_config(tmp_path, noted.model_copy(update={"seeds": 3}))


def test_a_study_may_grow_by_variants_and_tasks_but_not_change_its_cells(tmp_path):
    """Adding a variant (a new candidate) or a task to a running study keeps every cell trained
    so far valid, so it is taken; changing or dropping a variant, or a new variant together with
    another change, is refused as any changed config is."""
    _, cfg = study.load(str(SMOKE))
    study.pin_config(tmp_path, cfg)
    extra = study.Variant(name="more", method="collodreamer", overrides=["planner.iters=2"])
    grown = cfg.model_copy(update={"variants": [*cfg.variants, extra]})
    assert study.pin_config(tmp_path, grown) == ["variant more"]
    assert "planner.iters=2" in (tmp_path / "study.yaml").read_text()
    assert study.pin_config(tmp_path, grown) == []  # stored: the grown study resumes
    relabelled = extra.model_copy(update={"label": "More updates"})  # a label is the report's
    grown = grown.model_copy(update={"variants": [*cfg.variants, relabelled]})
    assert study.pin_config(tmp_path, grown) == []
    more_tasks = grown.model_copy(update={"tasks": [*grown.tasks, "cheetah_run"]})
    assert study.pin_config(tmp_path, more_tasks) == ["task cheetah_run"]
    changed = cfg.variants[0].model_copy(update={"overrides": ["planner.iters=3"]})
    for bad in (
        more_tasks.model_copy(update={"variants": [changed, *more_tasks.variants[1:]]}),
        more_tasks.model_copy(update={"variants": more_tasks.variants[1:]}),
        more_tasks.model_copy(
            update={
                "variants": [*more_tasks.variants, extra.model_copy(update={"name": "again"})],
                "steps": 1200,
            }
        ),
    ):
        with pytest.raises(study.StudyError, match="adding variants or tasks is taken"):
            study.pin_config(tmp_path, bad)


def test_comparison_study_is_the_issue_grid():
    _, cfg = study.load("comparison")
    keys = [c.key for c in study.cells(cfg)]
    assert len(keys) == 15 and cfg.seeds == 3 and cfg.steps == 100_000
    paper = [c for c in study.cells(cfg) if c.variant.name == "paper"]
    assert {c.task: c.steps for c in paper} == {
        "cheetah_run": 25_000,
        "quadruped_walk": 30_000,
        "reacher_easy": 25_000,
    }
    run_cfg = study.run_config(paper[0])
    assert run_cfg.wm.deter == 300 and run_cfg.value.mode == "plan_inner"
    assert run_cfg.planner.value_lambda == 1.0 and run_cfg.value.clip
    assert run_cfg.value.norm == "batch" and run_cfg.value.dropout > 0


def _study(args: list[str], tmp: Path) -> subprocess.CompletedProcess:
    # One XLA device, as the in-process tests: the cells' programs are then those of
    # test_methods.py (same configs), which the persistent compile cache shares.
    env = {
        **os.environ,
        "XLA_FLAGS": f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=1",
    }
    cmd = [sys.executable, str(ROOT / "study.py"), *args, str(SMOKE)]
    cmd += ["--root", str(tmp / "runs"), "--results", str(tmp / "results")]
    cmd += ["--out", str(tmp / "report" / "smoke.md")]
    return subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, env=env, timeout=900)


@pytest.mark.heavy
def test_smoke_study_runs_resumes_without_retraining_and_reports(tmp_path):
    # Stopped after its first cell, as an interrupted study is left.
    first = _study(["run", "--max-cells", "1", "--no-report"], tmp_path)
    assert first.returncode == 0, first.stdout + first.stderr
    cell1 = tmp_path / "runs" / "reacher_easy" / "collodreamer"
    assert study.checkpoint_steps(cell1)[-1] == 800
    assert not (tmp_path / "runs" / "reacher_easy" / "dreamer").exists()
    metrics1 = (cell1 / "metrics.jsonl").read_text()

    # Re-run: the finished cell is skipped, the other trains, the report is written. Dreamer's
    # cell trains its two seeds as two programs (seeds_per_program: 1), each keyed as seed 0 and
    # seed 1 of one vmapped run, and its record merges them.
    second = _study(["run"], tmp_path)
    assert second.returncode == 0, second.stdout + second.stderr
    assert "reacher_easy/collodreamer: finished, skipped" in second.stdout
    assert (cell1 / "metrics.jsonl").read_text() == metrics1  # not retrained
    dreamer = tmp_path / "runs" / "reacher_easy" / "dreamer"
    for part, seed in (("seed0", 0), ("seed1", 1)):
        assert study.checkpoint_steps(dreamer / part)[-1] == 800
        assert json.loads((dreamer / part / "seeds.json").read_text()) == [{"seed": seed}]
    assert "--first-seed 1" in (dreamer / "seed1" / "train.log").read_text()
    for variant in ("collodreamer", "dreamer"):
        small = tmp_path / "results" / "reacher_easy" / variant
        assert {p.name for p in small.iterdir()} >= {"config.yaml", "metrics.jsonl", "host.json"}
    record = tmp_path / "results" / "reacher_easy" / "dreamer"
    assert json.loads((record / "seeds.json").read_text()) == [{"seed": 0}, {"seed": 1}]
    # each part trained its own seed's key (one key for both would give equal losses)
    losses = [
        [
            r["wm/loss/total"]
            for r in map(json.loads, (dreamer / part / "metrics.jsonl").read_text().splitlines())
            if r["kind"] == "train"
        ]
        for part in ("seed0", "seed1")
    ]
    assert losses[0] and losses[0] != losses[1]
    assert [h["seeds"] for h in json.loads((record / "host.json").read_text())] == [[0], [1]]
    finals = [
        r
        for r in map(json.loads, (record / "metrics.jsonl").read_text().splitlines())
        if r["kind"] == "eval" and r["step"] == 800
    ]
    assert sorted(r["seed"] for r in finals) == [0, 1]

    md = (tmp_path / "report" / "smoke.md").read_text()
    assert "(partial)" not in md
    assert "![reacher_easy](smoke/reacher_easy.png)" in md
    assert (tmp_path / "report" / "smoke" / "reacher_easy.png").stat().st_size > 1000
    assert (tmp_path / "report" / "smoke" / "profile_800.png").stat().st_size > 1000 and "IQM" in md
    assert "| collodreamer (n=2) |" in md and "| dreamer (n=2) |" in md
    assert "*random policy*" in md and "cpu" in md

    # A third run trains nothing.
    third = _study(["run", "--no-report"], tmp_path)
    assert third.returncode == 0 and third.stdout.count("finished, skipped") == 2

    # The run directories wiped (a fresh clone, a cleaned scratch disk): the committed record
    # says both cells finished, so nothing retrains.
    import shutil

    shutil.rmtree(tmp_path / "runs")
    fourth = _study(["run", "--no-report"], tmp_path)
    assert fourth.returncode == 0, fourth.stdout + fourth.stderr
    assert fourth.stdout.count("finished in the committed record") == 2
    assert not (tmp_path / "runs" / "reacher_easy").exists()

    # Only seed 0 of dreamer's cell in the record (seed 1's part was lost with its machine before
    # it finished): the study trains seed 1's program alone, and the record keeps seed 0.
    rows = [json.loads(x) for x in (record / "metrics.jsonl").read_text().splitlines()]
    seed0 = [r for r in rows if r["seed"] == 0]
    (record / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in seed0))
    (record / "seeds.json").write_text(json.dumps([{"seed": 0}]))
    hosts = json.loads((record / "host.json").read_text())
    (record / "host.json").write_text(json.dumps(hosts[:1]))
    status = subprocess.run(
        [
            sys.executable,
            str(ROOT / "study.py"),
            "status",
            str(SMOKE),
            "--root",
            str(tmp_path / "runs"),
            "--results",
            str(tmp_path / "results"),
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )
    assert "seed0 finished (committed record), seed1 not started" in status.stdout, status.stdout
    fifth = _study(["run", "--no-report"], tmp_path)
    assert fifth.returncode == 0, fifth.stdout + fifth.stderr
    assert "reacher_easy/dreamer seed0: finished in the committed record, skipped" in fifth.stdout
    assert "reacher_easy/dreamer seed1 (seed 1 of 2): training" in fifth.stdout
    assert not (tmp_path / "runs" / "reacher_easy" / "dreamer" / "seed0").exists()
    merged = [json.loads(x) for x in (record / "metrics.jsonl").read_text().splitlines()]
    assert [r for r in merged if r["seed"] == 0] == seed0  # kept as recorded
    assert {r["seed"] for r in merged if r["kind"] == "eval" and r["step"] == 800} == {0, 1}


def test_a_committed_record_counts_as_finished_only_when_whole_and_of_the_same_config(tmp_path):
    _, cfg = study.load(str(SMOKE))
    cell = study.cells(cfg)[0]
    rec = tmp_path / cell.task / cell.variant.name
    rec.mkdir(parents=True)
    from mjx_collo import config as config_lib

    config_lib.dump_yaml(study.run_config(cell), rec / "config.yaml")
    rows = [
        {"step": step, "seed": seed, "kind": "eval", "eval/return": 1.0}
        for step in (cell.steps // 2, cell.steps)
        for seed in range(cell.seeds)
    ]
    (rec / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows[:-1]) + "\n")
    assert not study.recorded_finished(tmp_path, cell)  # one seed's final evaluation missing
    (rec / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    assert study.recorded_finished(tmp_path, cell)
    changed = yaml.safe_load((rec / "config.yaml").read_text())
    changed["wm"]["cnn_depth"] += 8  # inert in a state run (a pixel default changed since)
    (rec / "config.yaml").write_text(yaml.safe_dump(changed))
    assert study.recorded_finished(tmp_path, cell)
    changed["planner"]["iters"] += 1
    (rec / "config.yaml").write_text(yaml.safe_dump(changed))
    assert not study.recorded_finished(tmp_path, cell)  # trained under another config


def test_partial_study_reports_what_exists_and_marks_the_rest(tmp_path):
    """One cell with two evaluations and the other missing: the report shows the first with
    bootstrap CIs and lists the missing cell; it does not fail."""
    _, cfg = study.load(str(SMOKE))
    cell = tmp_path / "results" / "reacher_easy" / "collodreamer"
    cell.mkdir(parents=True)
    rows = []
    for step, returns in ((400, (10.0, 30.0)), (800, (50.0, 70.0))):
        for seed, r in enumerate(returns):
            rows.append(
                {
                    "step": step,
                    "seed": seed,
                    "kind": "train",
                    "perf/wall_s": step / 10,
                    "perf/env_steps_per_s": 40.0,
                }
            )
            rows.append({"step": step, "seed": seed, "kind": "eval", "eval/return": r})
    (cell / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + '\n{"step": 9')
    # two launches: one recorded before host.json named the CPU, one after (speeds differ ~2x
    # between VMs, so the cost row says where each part ran)
    cpu = "AMD EPYC, avx512f, 2 cores"
    (cell / "host.json").write_text(
        json.dumps([{"platform": "cpu"}, {"platform": "cpu", "cpu": cpu}])
    )
    out = report.write("smoke", cfg, tmp_path / "results", tmp_path / "smoke.md")
    md = out.read_text()
    cost = next(x for x in md.split("## Cost")[1].splitlines() if x.startswith("| reacher_easy |"))
    assert cost.endswith(f"| cpu; cpu: {cpu} |")
    assert md.startswith("# Study: smoke (partial)")
    assert "- reacher_easy/dreamer: 0 of 800 env steps" in md
    line = next(x for x in md.splitlines() if x.startswith("| collodreamer (n=2) |"))
    mean, lo, hi = 60.0, 50.0, 70.0
    assert f"{mean:.0f} [{lo:.0f}, {hi:.0f}]" in line
    assert "| *random policy* | 43.1 |" in md  # an anchor: a row, in its budget's column


def test_a_cell_still_training_shows_its_last_evaluation_in_the_table(tmp_path):
    """A cell stopped at 400 of 800 env steps (a study across sessions): its row shows the last
    evaluation, named as partial, rather than a dash; a finished cell shows its budget's return."""
    _, cfg = study.load(str(SMOKE))
    for variant, steps in (("collodreamer", (400, 800)), ("dreamer", (400,))):
        cell = tmp_path / "results" / "reacher_easy" / variant
        cell.mkdir(parents=True)
        rows = []
        for step in steps:
            for seed, r in enumerate((step / 10, step / 10 + 20)):
                rows.append({"step": step, "seed": seed, "kind": "train", "perf/wall_s": 1.0})
                rows.append({"step": step, "seed": seed, "kind": "eval", "eval/return": r})
        (cell / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    md = report.write("smoke", cfg, tmp_path / "results", tmp_path / "smoke.md").read_text()
    assert "- reacher_easy/dreamer: 400 of 800 env steps\n" in md
    row = {x.split(" |")[0]: x for x in md.splitlines() if x.startswith("| ") and "(n=2)" in x}
    assert row["| collodreamer (n=2)"].endswith("| 90 [80, 100] |")
    assert row["| dreamer (n=2)"].endswith("| 50 [40, 60] at 400 (partial) |")
    # dreamer trains in parts (one seed per program): only its first part begun
    dreamer = tmp_path / "results" / "reacher_easy" / "dreamer" / "metrics.jsonl"
    dreamer.write_text("".join(x + "\n" for x in dreamer.read_text().splitlines()[:2]))
    md = report.write("smoke", cfg, tmp_path / "results", tmp_path / "smoke.md").read_text()
    assert "- reacher_easy/dreamer: 400 of 800 env steps, 1 of 2 runs started\n" in md


def test_a_budget_between_evaluations_reads_the_last_evaluation_before_it():
    """The comparison's 100k cells evaluate every 10k; the paper's budget for cheetah is 25k. Its
    column shows the 20k evaluation, named by its step (no more data than the budget allows),
    rather than a dash; a run that has not reached the budget yet is also marked partial."""
    s = report.Series(label="x", env_steps=100_000, runs=2)
    s.evals = {k: np.array([k / 1000, k / 1000 + 20.0]) for k in (10_000, 20_000, 30_000)}
    assert report._score(s, 25_000, 100_000) == "30 [20, 40] at 20k"
    assert report._score(s, 30_000, 100_000) == "40 [30, 50]"
    s.env_steps = 22_000
    assert report._score(s, 25_000, 100_000) == "30 [20, 40] at 20k (partial)"
    # a cell whose own budget ends before this column (the paper preset at 25k, column 100k)
    assert report._score(s, 100_000, 25_000) == "—"


def test_a_prior_runs_prior_alone_evaluations_are_a_series_of_their_own(tmp_path):
    """A cell whose runs log ``eval/return_prior`` (a policy-prior run) reports it as a second
    series, "<variant>, prior alone", in the task table, with no cost row of its own."""
    _, cfg = study.load(str(SMOKE))
    cell = tmp_path / "results" / "reacher_easy" / "collodreamer"
    cell.mkdir(parents=True)
    rows = []
    for step in (400, 800):
        for seed, (r, p) in enumerate(((50.0, 80.0), (70.0, 100.0))):
            rows.append({"step": step, "seed": seed, "kind": "train", "perf/wall_s": 1.0})
            rows.append(
                {
                    "step": step,
                    "seed": seed,
                    "kind": "eval",
                    "eval/return": r,
                    "eval/return_prior": p,
                }
            )
    (cell / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    variant = next(v for v in cfg.variants if v.name == "collodreamer")
    planned, prior = report.load_cell(cell, variant)
    assert planned.label == "collodreamer" and prior.label == "collodreamer, prior alone"
    np.testing.assert_array_equal(planned.at(800), [50.0, 70.0])
    np.testing.assert_array_equal(prior.at(800), [80.0, 100.0])
    md = report.write("smoke", cfg, tmp_path / "results", tmp_path / "smoke.md").read_text()
    assert next(x for x in md.splitlines() if x.startswith("| collodreamer, prior alone (n=2) |"))
    assert "prior alone" in md.split("## Cost")[0]
    assert "prior alone" not in md.split("## Cost")[1].split("##")[0]
    assert np.isclose(report._ci(np.array([50.0, 70.0]))[0], 60.0)


def test_quadruped_reports_show_the_starts_on_their_feet_and_the_get_ups(tmp_path):
    """A quadruped figure is mostly how many evaluation starts landed on their feet: a cell whose
    evaluations log the task's facts (Env.eval_metrics) reports them beside its table, summed over
    seeds, out of the episodes its config.yaml ran; the prior alone shares them (same episodes)."""
    _, cfg = study.load(str(SMOKE))
    cell = tmp_path / "results" / "reacher_easy" / "collodreamer"
    cell.mkdir(parents=True)
    rows = []
    for step in (400, 800):
        for seed, (feet, up) in enumerate(((1.0, 0.0), (2.0, 1.0))):
            rows.append({"step": step, "seed": seed, "kind": "train", "perf/wall_s": 1.0})
            rows.append(
                {
                    "step": step,
                    "seed": seed,
                    "kind": "eval",
                    "eval/return": 100.0,
                    "eval/return_prior": 90.0,
                    "eval/starts_on_feet": feet,
                    "eval/got_up": up * (step == 800),
                }
            )
    (cell / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    (cell / "config.yaml").write_text("run:\n  eval_episodes: 5\n")
    md = report.write("smoke", cfg, tmp_path / "results", tmp_path / "smoke.md").read_text()
    line = next(x for x in md.splitlines() if x.startswith("| collodreamer | "))
    assert line == "| collodreamer | 3 of 10 on feet, 1 of 7 got up |", line
    facts = md.split("Evaluation starts on their feet")[1].split("## Aggregate")[0]
    assert line in facts and "prior alone" not in facts
    # evaluations that also count the starts on their feet that fell (logged since 2026-12-07)
    for r in rows:
        if r["kind"] == "eval":
            r["eval/fell"] = r["eval/starts_on_feet"] - 1.0
    (cell / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    md = report.write("smoke", cfg, tmp_path / "results", tmp_path / "smoke.md").read_text()
    line = next(x for x in md.splitlines() if x.startswith("| collodreamer | "))
    assert line == "| collodreamer | 3 of 10 on feet (1 fell), 1 of 7 got up |", line
    # a cell still training towards the budget: its facts are read at the same last evaluation
    # as its return (here 400 of 800), named so, rather than a dash beside a return
    rows = [r for r in rows if r["step"] == 400]
    (cell / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    md = report.write("smoke", cfg, tmp_path / "results", tmp_path / "smoke.md").read_text()
    facts = md.split("Evaluation starts on their feet")[1].split("## Aggregate")[0]
    line = next(x for x in facts.splitlines() if x.startswith("| collodreamer | "))
    assert line == "| collodreamer | 3 of 10 on feet (1 fell), 0 of 7 got up at 400 (partial) |", (
        line
    )


def test_ablation_study_is_the_issue_grid():
    """Seven sections on cheetah_run, 3 seeds x 50k; the plan objective on reacher_easy too; the
    default runs once for all the sections that compare against it; discount is one sweep."""
    _, cfg = study.load("ablations")
    assert (cfg.seeds, cfg.steps) == (3, 50_000) and len(cfg.sections) == 7
    cells = study.cells(cfg)
    on = {t: {c.variant.name for c in cells if c.task == t} for t in cfg.tasks}
    assert on["reacher_easy"] == {"default", "no_value", "end_bootstrap"}
    for sec in cfg.sections:
        names = {v.name for v in cfg.variants if sec.name in v.sections}
        assert len(names & on["cheetah_run"]) >= (1 if sec.name == "discount" else 2), sec.name
    assert sum(c.variant.name == "default" for c in cells) == 2  # once per task
    sweep = next(v for v in cfg.variants if v.name == "discount").sweep
    assert sweep == "value.gamma+planner.gamma=0.9,0.95,0.99"


def test_a_study_with_sections_reports_each_with_its_variants(tmp_path):
    path = _study_yaml(
        tmp_path,
        sections=[
            {"name": "a", "title": "Section A", "paper": "The paper says A."},
            {"name": "b", "title": "Section B", "finding": "B matters."},
        ],
        variants=[
            {
                "name": "collodreamer",
                "method": "collodreamer",
                "presets": ["debug"],
                "sections": ["a", "b"],
            },
            {"name": "dreamer", "method": "dreamer", "presets": ["debug"], "sections": ["b"]},
        ],
    )
    _, cfg = study.load(str(path))
    for variant, r in (("collodreamer", 11.0), ("dreamer", 22.0)):
        cell = tmp_path / "results" / "reacher_easy" / variant
        cell.mkdir(parents=True)
        rows = [
            {"step": 800, "seed": s, "kind": k, "eval/return": r + s, "perf/wall_s": 1.0}
            for s in (0, 1)
            for k in ("train", "eval")
        ]
        (cell / "metrics.jsonl").write_text("\n".join(json.dumps(x) for x in rows) + "\n")
    md = report.write("s", cfg, tmp_path / "results", tmp_path / "s.md").read_text()
    a, b = md.split("## Section A")[1].split("## Section B")
    assert "**The paper:** The paper says A." in a and "to be written" in a
    assert "| collodreamer (n=2) |" in a and "| dreamer (n=2) |" not in a
    assert "**Here:** B matters." in b and "| dreamer (n=2) |" in b
    assert (tmp_path / "s" / "a_reacher_easy.png").exists()
    with pytest.raises(study.StudyError, match="names sections"):
        study.load(
            str(
                _study_yaml(
                    tmp_path, variants=[{"name": "x", "method": "latco", "sections": ["nope"]}]
                )
            )
        )


def _fake_part(part: Path, cell, seed: int, last: int, value: float) -> None:
    """A part's run directory as train.py leaves it: rows to ``last`` env steps, a checkpoint
    there (only its step is read here)."""
    from mjx_collo import config as config_lib

    part.mkdir(parents=True)
    config_lib.dump_yaml(study.run_config(cell), part / "config.yaml")
    rows = [
        {"step": step, "seed": 0, "kind": kind, "eval/return": value, "perf/wall_s": step / 10}
        for step in range(400, last + 1, 400)
        for kind in ("train", "eval")
    ]
    (part / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    (part / "seeds.json").write_text(json.dumps([{"seed": seed}]))
    (part / "host.json").write_text(json.dumps([{"platform": "cpu"}]))
    (part / "checkpoints" / str(last)).mkdir(parents=True)


def test_a_cell_in_parts_merges_into_its_record_and_never_goes_back(tmp_path):
    """The smoke study's dreamer cell trains one seed per program. Its record merges the parts,
    keeps a part's recorded rows when this machine's copy of it is behind them, a part that
    finished here but missed the record is collected by the next study run (which trains
    nothing), and a record short of seeds is reported partial."""
    _, cfg = study.load(str(SMOKE))
    cell = next(c for c in study.cells(cfg) if c.variant.name == "dreamer")
    root, results = tmp_path / "runs", tmp_path / "results"
    top = study.cell_dir(root, cell)
    _fake_part(top / "seed0", cell, 0, 800, 10.0)
    _fake_part(top / "seed1", cell, 1, 400, 20.0)
    rec = study.collect(root, cell, results)
    assert json.loads((rec / "seeds.json").read_text()) == [{"seed": 0}, {"seed": 1}]
    assert study.recorded_finished(results, cell, [0])
    assert not study.recorded_finished(results, cell, [1])
    assert not study.recorded_finished(results, cell)
    hosts = json.loads((rec / "host.json").read_text())
    assert [h["seeds"] for h in hosts] == [[0], [1]]

    # seed 1 finished on another machine (the record), this machine's seed1 stopped at 400
    rows = [json.loads(x) for x in (rec / "metrics.jsonl").read_text().splitlines()]
    rows += [{"step": 800, "seed": 1, "kind": k, "eval/return": 30.0} for k in ("train", "eval")]
    (rec / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    study.collect(root, cell, results)
    assert study.recorded_finished(results, cell)  # not overwritten by the copy behind it

    # seed 0 finished here but its rows never reached the record (killed before collecting)
    kept = [r for r in rows if r["seed"] == 1]
    (rec / "metrics.jsonl").write_text("".join(json.dumps({**r, "seed": 0}) + "\n" for r in kept))
    (rec / "seeds.json").write_text(json.dumps([{"seed": 1}]))
    out = report.write("smoke", cfg, results, tmp_path / "smoke.md").read_text()
    assert "- reacher_easy/dreamer: 1 of 2 runs" in out and "(partial)" in out
    run = _study(["run", "--no-report", "--only", "dreamer"], tmp_path)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "dreamer seed0: finished, skipped" in run.stdout
    assert "dreamer seed1: finished in the committed record, skipped" in run.stdout
    assert study.recorded_finished(results, cell)
    assert json.loads((rec / "seeds.json").read_text()) == [{"seed": 0}, {"seed": 1}]


def test_report_confidence_intervals_are_the_same_each_time_it_is_written():
    """rliable's bootstrap resamples with NumPy's global RNG whatever random_state it is given;
    the report seeds it, so regenerating a committed report changes no number (it did), and
    leaves the caller's RNG where it was."""
    scores = np.array([120.0, 310.0, 200.0, 95.0, 400.0])
    np.random.seed(123)
    before = np.random.get_state()[1].copy()
    first = report._ci(scores)
    np.random.random(1000)  # another use of the global RNG between two reports
    assert report._ci(scores) == first
    np.random.seed(123)
    report._ci(scores)
    assert (np.random.get_state()[1] == before).all()

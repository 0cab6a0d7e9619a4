"""``make combine``: seeds from separate run directories become one metrics file, plots and a
per-seed eval summary; runs of different configs are refused with the differing key named.
Host-side only (metrics files written here stand in for two finished train.py runs)."""

from __future__ import annotations

import json

import pytest
import yaml

from mjx_collo import combine


def fake_run(path, seed, evals, lr=6e-4, seeds_in_run=1):
    path.mkdir(parents=True)
    cfg = {"method": "collodreamer", "run": {"seed": seed, "steps": 20000}, "wm": {"lr": lr}}
    (path / "config.yaml").write_text(yaml.safe_dump(cfg))
    rows = []
    for step, per_seed in evals.items():
        for i in range(seeds_in_run):
            rows.append({"step": step, "seed": i, "kind": "train", "train/return": 1.0 + i})
            rows.append({"step": step, "seed": i, "kind": "eval", "eval/return": per_seed[i]})
    (path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return path


def test_seeds_of_separate_runs_combine_into_one_curve_and_summary(tmp_path):
    a = fake_run(tmp_path / "a", 0, {10000: [10.0], 20000: [30.0]})
    b = fake_run(tmp_path / "b", 1, {10000: [20.0, 40.0], 20000: [50.0, 70.0]}, seeds_in_run=2)
    out = tmp_path / "out"
    summary = combine.combine([a, b], out)
    assert summary["eval_return"]["20000"] == {
        "per_seed": [30.0, 50.0, 70.0],
        "mean": 50.0,
        "seeds": 3,
    }
    assert summary["eval_return"]["10000"]["mean"] == pytest.approx(70 / 3, abs=0.05)
    assert [s["run"] for s in summary["seeds"]] == [str(a), str(b), str(b)]
    rows = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    assert {r["seed"] for r in rows} == {0, 1, 2}
    assert (out / "plots" / "returns.png").stat().st_size > 1000
    # combining again into the same directory replaces, not appends
    combine.combine([a, b], out)
    assert len((out / "metrics.jsonl").read_text().splitlines()) == len(rows)


def test_runs_of_different_configs_are_refused_naming_the_key(tmp_path):
    a = fake_run(tmp_path / "a", 0, {10000: [10.0]})
    b = fake_run(tmp_path / "b", 1, {10000: [20.0]}, lr=1e-3)
    with pytest.raises(SystemExit, match=r"wm\.lr: 0\.0006 \(run 0\) vs 0\.001 \(run 1\)"):
        combine.combine([a, b], tmp_path / "out")
    summary = combine.combine([a, b], tmp_path / "out", force=True)
    assert summary["config_differences"] and summary["eval_return"]["10000"]["mean"] == 15.0


def test_a_directory_without_metrics_is_named(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit, match="empty: no metrics.jsonl"):
        combine.combine([tmp_path / "empty"], tmp_path / "out")


def test_a_key_added_since_a_run_was_written_is_not_a_difference(tmp_path):
    """A run written before `env.obs` existed ran with its value, 'state' (config.ADDED_KEYS)."""
    old = fake_run(tmp_path / "old", 0, {10000: [10.0]})
    new = fake_run(tmp_path / "new", 1, {10000: [20.0]})
    cfg = yaml.safe_load((old / "config.yaml").read_text())
    cfg["env"] = {"task": "cheetah_run"}
    (old / "config.yaml").write_text(yaml.safe_dump(cfg))
    cfg["env"] = {"task": "cheetah_run", "obs": "state"}
    (new / "config.yaml").write_text(yaml.safe_dump(cfg))
    assert combine.combine([old, new], tmp_path / "out")["config_differences"] == []
    cfg["env"] = {"task": "cheetah_run", "obs": "pixels"}
    (new / "config.yaml").write_text(yaml.safe_dump(cfg))
    with pytest.raises(SystemExit, match=r"env\.obs: 'state' \(run 0\) vs 'pixels' \(run 1\)"):
        combine.combine([old, new], tmp_path / "out")


def test_the_conv_depth_of_a_state_run_is_not_a_difference(tmp_path):
    """wm.cnn_depth sizes the pixel encoder: two state runs that differ only there are one
    experiment (its default may change for pixel runs); two pixel runs are not."""
    a = fake_run(tmp_path / "a", 0, {10000: [10.0]})
    b = fake_run(tmp_path / "b", 1, {10000: [20.0]})
    for run, depth, obs in ((a, 32, "state"), (b, 16, "state")):
        cfg = yaml.safe_load((run / "config.yaml").read_text())
        cfg["env"] = {"task": "cheetah_run", "obs": obs}
        cfg.setdefault("wm", {})["cnn_depth"] = depth
        (run / "config.yaml").write_text(yaml.safe_dump(cfg))
    assert combine.combine([a, b], tmp_path / "out")["config_differences"] == []
    for run in (a, b):
        cfg = yaml.safe_load((run / "config.yaml").read_text())
        cfg["env"]["obs"] = "pixels"
        (run / "config.yaml").write_text(yaml.safe_dump(cfg))
    with pytest.raises(SystemExit, match=r"wm\.cnn_depth: 32 \(run 0\) vs 16 \(run 1\)"):
        combine.combine([a, b], tmp_path / "out")

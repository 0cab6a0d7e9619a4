"""Evaluate a checkpoint: ``make eval CKPT=<run dir or checkpoint step dir> [EPISODES=10] [VIDEO=1]``.

Deterministic episodes (no exploration noise) per seed with the saved parameters — the replay is
not loaded. Prints a table of mean ± std return, writes ``eval_<step>.json`` (and with ``--video`` a GIF of
one episode per seed, rendered on the CPU) next to the checkpoints. For a pixel run (``env.obs=pixels``)
the video also comes as ``eval_<step>_run<i>_agent.gif``: the 64x64 frames the agent saw. A run
with a policy prior (``planner.init: policy_cem``) also reports the prior acting alone on the same
episodes (``prior_mean_over_runs``), as its training evaluations log ``eval/return_prior``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def parse(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--ckpt", required=True, help="run directory or <run>/checkpoints/<step>")
    p.add_argument("--episodes", type=int, default=10)
    p.add_argument("--video", action="store_true", help="write a GIF of episode 0 of each seed")
    p.add_argument("--size", type=int, default=128, help="video frame size in pixels")
    p.add_argument("--out", default=None, help="output directory (default: the run directory)")
    p.add_argument(
        "overrides",
        nargs="*",
        help="planner settings to evaluate with instead of the trained ones, e.g. "
        "planner.mpc_steps=5 planner.iters=400 (only planner.* keys: the rest shapes the networks)",
    )
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse(argv)
    import jax
    import numpy as np

    import envs
    from mjx_collo import checkpoint, config, parallel, session, trainer

    session.exit_on_signal("evaluating")
    session.setup_jax()
    skipped = checkpoint.report_skips(lambda line: print(line, file=sys.stderr))
    try:
        ckpt = checkpoint.Checkpointer(args.ckpt, read_only=True)
        _, meta = ckpt.newest_meta(on_skip=skipped)
        cfg = ckpt.config_of(meta)
        cfg_run = session.eval_config(cfg, args.overrides)
    except (checkpoint.CheckpointError, FileNotFoundError, config.ConfigError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.episodes < 1:
        print("error: --episodes must be >= 1", file=sys.stderr)
        return 2
    cfg_eval = cfg_run.model_copy(
        update={"run": cfg.run.model_copy(update={"eval_episodes": args.episodes})}
    )
    env = envs.from_config(cfg.env)
    try:
        tr = trainer.make_train(cfg_eval, env)
    except config.ConfigError as e:  # an override that this checkpoint's agent cannot act with
        print(f"error: {e}", file=sys.stderr)
        return 2
    labels = meta["labels"]
    n = meta["num_runs"]
    try:
        state, keys, step = session.restore_state(ckpt, cfg, env, meta, on_skip=skipped)
    except checkpoint.CheckpointError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    t = time.perf_counter()
    eval_keys = jax.vmap(lambda k: jax.random.fold_in(jax.random.fold_in(k, step), 7))(keys)
    evaluate_fn = parallel.batched(tr)[2]  # one seed runs unbatched (parallel.over_seeds)
    out = jax.device_get(evaluate_fn(state, eval_keys))
    secs = time.perf_counter() - t
    returns = np.asarray(out["returns"])  # [S, episodes]
    run_dir = ckpt.directory.parent
    out_dir = Path(args.out) if args.out else run_dir
    out_dir.mkdir(parents=True, exist_ok=True)

    print(
        f"{cfg.method} on {cfg.env.task}, checkpoint at {step} env steps, "
        f"{args.episodes} deterministic episode(s) per run ({secs:.0f}s incl. compile)"
    )
    print(f"{'run':<32s} {'mean':>8s} {'std':>8s} {'min':>8s} {'max':>8s}")
    rows = []
    for i, lab in enumerate(labels):
        r = returns[i]
        name = ", ".join(f"{k}={v}" for k, v in lab.items())
        print(f"{name:<32s} {r.mean():8.1f} {r.std():8.1f} {r.min():8.1f} {r.max():8.1f}")
        rows.append(
            {"run": lab, "returns": r.tolist(), "mean": float(r.mean()), "std": float(r.std())}
        )
    means = returns.mean(1)
    print(f"{'all runs':<32s} {means.mean():8.1f} {means.std():8.1f}")
    task = {k: np.asarray(v) for k, v in out["task"].items()}  # Env.eval_metrics, e.g. quadruped's
    if task:
        for i, row in enumerate(rows):
            row["task"] = {k: float(v[i]) for k, v in task.items()}
        print(
            "task facts per run: "
            + "; ".join(", ".join(f"{k} {v:.0f}" for k, v in row["task"].items()) for row in rows)
        )
    prior = np.asarray(out["returns_prior"]) if "returns_prior" in out else None
    if prior is not None:  # the policy prior acting alone on the same episodes
        for row, r in zip(rows, prior, strict=True):
            row.update(prior_returns=r.tolist(), prior_mean=float(r.mean()))
        print(f"{'the prior alone, all runs':<32s} {prior.mean(1).mean():8.1f}")
    result = {
        "task": cfg.env.task,
        "method": cfg.method,
        "env_steps": step,
        "episodes": args.episodes,
        "overrides": list(args.overrides),
        "planner": config.to_dict(cfg_run)["planner"],  # the settings the episodes acted with
        "runs": rows,
        "mean_over_runs": float(means.mean()),
        "std_over_runs": float(means.std()),
    }
    if prior is not None:
        result["prior_mean_over_runs"] = float(prior.mean(1).mean())
    if args.video:
        import imageio

        from envs import render

        videos = []
        sizes = [("", args.size)]
        if cfg.env.obs == "pixels":  # what the agent saw: the observation camera at its size
            sizes.append(("_agent", env.size))  # env is envs.PixelObs
        for i in range(n):
            target = out.get("target_xy")
            for suffix, size in sizes:
                frames = render.render_episode(
                    env.unwrapped,
                    np.asarray(out["qpos"][i]),
                    None if target is None else np.asarray(target[i]),
                    size,
                    size,
                )
                path = out_dir / f"eval_{step}_run{i}{suffix}.gif"
                imageio.mimsave(
                    path,
                    list(frames),
                    duration=1000 * env.unwrapped.dt * cfg.env.action_repeat,
                    loop=0,
                )
                videos.append(str(path))
                print(f"video: {path}")
        result["videos"] = videos
    # one file per checkpoint step: evaluating another checkpoint does not overwrite this one
    path = out_dir / f"eval_{step}.json"
    path.write_text(json.dumps(result, indent=1))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    from mjx_collo import xla_log_filter

    xla_log_filter.install()
    sys.exit(main())

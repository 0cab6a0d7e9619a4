"""Train an agent: ``make train ENV=cheetah [METHOD=] [SEEDS=] [STEPS=] [RUN=] [ARGS="a.b=c"]``.

CLI glue only: parse -> build the env -> hand it to mjx_collo.runner, which compiles, loops and
writes. Imports only the library (mjx_collo, envs).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mjx_collo import host_devices, session


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--env", default="cheetah", help="task name or alias (cheetah, reacher, ...)")
    p.add_argument(
        "--method",
        default="collodreamer",
        help="collodreamer | latco | dreamer | cem | mppi | mppi_value",
    )
    p.add_argument("--seeds", type=int, default=1, help="independent seeds, vmapped in one program")
    p.add_argument(
        "--first-seed",
        type=int,
        default=0,
        help="train seeds K..K+N-1 (N = --seeds): more seeds for a run, or a run's seeds as "
        "separate programs, each keyed as in one vmapped run",
    )
    p.add_argument("--steps", type=int, default=None, help="env steps (action repeat included)")
    p.add_argument("--run", default=None, help="run directory (default runs/<task>-<method>-...)")
    p.add_argument(
        "--sweep",
        default=None,
        help='float hyperparameters swept in the same compile: "value.gamma=0.9,0.99"',
    )
    p.add_argument("--preset", action="append", default=[], help="extra overlay, e.g. debug")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (log lines only)")
    p.add_argument(
        "--distributed",
        action="store_true",
        help="join a multi-process run via jax.distributed (see --coordinator)",
    )
    p.add_argument("--coordinator", default=None, help="host:port of process 0 (distributed)")
    p.add_argument("--num-processes", type=int, default=None)
    p.add_argument("--process-id", type=int, default=None)
    p.add_argument("overrides", nargs="*", help="dotted config overrides, e.g. wm.deter=300")
    return p.parse_args(argv)


def setup_distributed(args: argparse.Namespace) -> None:
    """Join a multi-process run (``--distributed``) before anything touches a JAX backend.

    Every process runs the same command with its own ``--process-id``; the seed axis is sharded
    over all processes' devices. On CPU the cross-process collectives go through gloo."""
    if not args.distributed:
        return
    import jax

    explicit = (args.coordinator, args.num_processes, args.process_id)
    if any(x is not None for x in explicit) and any(x is None for x in explicit):
        raise ValueError(
            "--distributed needs all of --coordinator host:port, --num-processes N and "
            "--process-id I (or none of them on a cluster JAX detects, e.g. SLURM)"
        )
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(
        coordinator_address=args.coordinator,
        num_processes=args.num_processes,
        process_id=args.process_id,
    )


def main(argv: list[str] | None = None) -> int:
    args = parse(argv)
    session.exit_on_signal("starting up (before the first chunk)")
    if not args.distributed:  # a distributed run's devices are its processes' own
        host_devices.configure(session.count_runs(args.seeds, args.sweep))
    try:
        setup_distributed(args)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    import envs
    from mjx_collo import config, runner
    from mjx_collo.checkpoint import CheckpointError

    try:
        task = envs.canonical(args.env)
        overrides = list(args.overrides)
        if args.steps is not None:
            overrides.append(f"run.steps={args.steps}")
        cfg = config.load(task=task, method=args.method, presets=args.preset, overrides=overrides)
        sweep = config.parse_sweep(args.sweep, cfg) if args.sweep else {}
        if args.seeds < 1:
            raise config.ConfigError(f"--seeds must be >= 1, got {args.seeds}")
        from mjx_collo import parallel

        parallel.check_first_seed(args.first_seed, sweep)
    except (envs.UnknownTaskError, config.ConfigError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2

    session.setup_jax()
    run_dir = (
        Path(args.run)
        if args.run
        else session.default_run_dir(
            task, args.method, args.seeds, args.preset, args.sweep, args.overrides, args.first_seed
        )
    )
    import jax

    if jax.process_index() == 0:  # one process of a distributed run holds the directory
        try:
            lock = session.lock_run_dir(run_dir)  # noqa: F841 (held until exit)
        except session.RunLocked as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
    print(
        f"mjx_collo: {args.method} on {task}, {args.seeds} seed(s)"
        + (f" from seed {args.first_seed}" if args.first_seed else "")
        + (f" x sweep {sweep}" if sweep else "")
        + f", {cfg.run.steps} env steps -> {run_dir}"
    )
    if args.distributed:
        print(
            f"jax.distributed: process {jax.process_index()}/{jax.process_count()}, "
            f"{jax.device_count()} devices ({jax.local_device_count()} on this process)"
        )
    env = envs.from_config(cfg.env)
    try:
        r = runner.Run(
            cfg,
            env,
            run_dir,
            num_seeds=args.seeds,
            sweep=sweep,
            progress=not args.no_progress,
            first_seed=args.first_seed,
        )
        if r.sharding is not None:
            devices = r.sharding.mesh.devices
            print(
                f"seed axis sharded over {devices.size} {devices.flat[0].platform} devices "
                f"({r.num_runs // devices.size} run(s) each)"
            )
        if r.eval_device is not None:
            print(
                f"evaluations run on {r.eval_device.platform} device {r.eval_device.id} while the "
                "next chunk trains (run.eval_overlap=false: in line, on the training device)"
            )
        result = r.run()
        r.close()
    except (CheckpointError, config.ConfigError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except runner.TrainingDiverged as e:
        print(f"error: {e}", file=sys.stderr)
        return 3
    if result.eval_returns:
        step, returns = result.eval_returns[-1]
        print(
            f"eval return at {step} env steps: {returns.mean():.1f} ± {returns.mean(1).std():.1f}"
            f" (mean ± std over {returns.shape[0]} run(s))"
        )
    print(
        f"{result.stopped} at {result.env_steps} env steps; results in {run_dir} "
        f"(metrics.jsonl, plots/, tb/, checkpoints/)"
    )
    return session.exit_code(result.stopped)


if __name__ == "__main__":
    from mjx_collo import xla_log_filter

    xla_log_filter.install()
    sys.exit(main())

"""How strongly would cloning the planner pull the policy prior, against Dreamer's objective?

``python benchmarks/probe_prior_terms.py RUN_DIR [RUN_DIR ...] [--batches 8]``

The prior's loss is ``actor.pg`` x Dreamer's objective through the model + ``actor.bc`` x the
squared error to the actions the agent took (docs/ALGORITHM.md §4.10). The two terms live on
different scales: the objective is a lambda-return (tens to hundreds), the cloning term a
squared error per action dimension (~1). On a run's newest checkpoint (with its replay) this
measures, per run, the global norm of each term's gradient with respect to the prior's
parameters on replay batches drawn as the learner draws them (the same starts subset), so a
cloning weight can be chosen that makes the pull of the data comparable to the model's: the
ratio |grad pg| / |grad bc| is the ``actor.bc`` at which the two gradients are of equal size.
Appends one entry per run directory to ``bench_results/prior_terms.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def probe(run: Path, batches: int) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np
    import optax

    import envs
    from mjx_collo import actor as actor_lib
    from mjx_collo import checkpoint, session
    from mjx_collo import replay as replay_lib
    from mjx_collo import world_model as wm_lib
    from mjx_collo.agent import uses_prior

    ck = checkpoint.Checkpointer(run, read_only=True)
    _, meta = ck.newest_meta()
    c = ck.config_of(meta)
    if not uses_prior(c):
        raise SystemExit(f"error: {run} has no policy prior (planner.init={c.planner.init})")
    env = envs.from_config(c.env)
    state, _, step = session.restore_state(ck, c, env, meta, replay=True)
    imag = wm_lib.imagination_model(c.wm)

    @jax.jit
    def norms(s, key):
        k_batch, k_wm, k_a, k_pick = jax.random.split(key, 4)
        batch = replay_lib.sample(s.replay, k_batch, c.replay.batch, c.replay.length)
        post = wm_lib.train_step(c.wm, s.wm, s.wm_opt, batch, k_wm, None)[3]
        starts = actor_lib.flatten_starts(post.state, 2)
        n = jax.tree.leaves(starts)[0].shape[0]
        if 0 < c.actor.starts < n:  # the learner's subset of imagination starts
            pick = jax.random.permutation(k_pick, n)[: c.actor.starts]
            starts = jax.tree.map(lambda x: x[pick], starts)
        starts = jax.lax.stop_gradient(starts)
        feat = jax.lax.stop_gradient(post.feat[:, :-1])
        act = batch["action"][:, 1:]  # the action taken from f_t is stored with row t+1
        bc = (
            feat.reshape(-1, feat.shape[-1]),
            act.reshape(-1, act.shape[-1]),
            (~batch["is_first"][:, 1:]).reshape(-1).astype(jnp.float32),
        )

        def pg(p):
            return actor_lib.actor_loss(p, c, imag, s.wm, s.value.target, starts, k_a)[0]

        g_pg = jax.grad(pg)(s.actor.params)["params"]
        g_bc = jax.grad(lambda p: actor_lib.bc_loss(c.actor, p, *bc))(s.actor.params)["params"]
        return optax.global_norm(g_pg), optax.global_norm(g_bc)

    rows = []
    for r in range(meta["num_runs"]):
        s = jax.tree.map(lambda x, r=r: x[r], state)
        out = np.array(
            [[float(x) for x in norms(s, jax.random.PRNGKey(i))] for i in range(batches)]
        )
        row = {
            "run": r,
            "grad_norm_pg": float(out[:, 0].mean()),
            "grad_norm_bc": float(out[:, 1].mean()),
            "ratio": float(np.mean(out[:, 0] / out[:, 1])),
        }
        rows.append(row)
        print(
            f"{run.name} ({c.env.task}, {step} env steps) run {r}: |grad pg| "
            f"{row['grad_norm_pg']:.3g}, |grad bc| {row['grad_norm_bc']:.3g}, ratio "
            f"{row['ratio']:.3g} (actor.pg={c.actor.pg:g}, actor.bc={c.actor.bc:g})"
        )
    return {
        "run": str(run),
        "task": c.env.task,
        "env_steps": int(step),
        "batches": batches,
        "runs": rows,
        "date": time.strftime("%Y-%m-%d"),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("runs", nargs="+", help="run directories of a policy-prior method")
    p.add_argument("--batches", type=int, default=8, help="replay batches averaged per run")
    p.add_argument("--out", default=str(ROOT / "bench_results" / "prior_terms.json"))
    args = p.parse_args(argv)
    from mjx_collo import session

    session.setup_jax()
    out = Path(args.out)
    rows = json.loads(out.read_text()) if out.exists() else []
    rows += [probe(Path(r), args.batches) for r in args.runs]
    out.write_text(json.dumps(rows, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    from mjx_collo import xla_log_filter

    xla_log_filter.install()
    sys.exit(main())

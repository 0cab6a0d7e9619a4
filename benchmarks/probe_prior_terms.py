"""How strongly would cloning the planner pull the policy prior, against Dreamer's objective?

``python benchmarks/probe_prior_terms.py RUN_DIR [RUN_DIR ...] [--batches 8]``

The prior's loss is ``actor.pg`` x Dreamer's objective through the model + ``actor.bc`` x the
squared error to the actions the agent took (docs/ALGORITHM.md §4.10). The two terms live on
different scales: the objective is a lambda-return (tens to hundreds), the cloning term a
squared error per action dimension (~1). On a run's newest checkpoint (with its replay) this
measures, per run, each term's gradient with respect to the prior's parameters, averaged over
replay batches drawn as the learner draws them (the same starts subset): the ratio of their
norms |grad pg| / |grad bc| is the ``actor.bc`` at which the two pull equally, and their cosine
says whether they pull the same way. Measured on one checkpoint: the ratio changes as training
goes (the objective's gradient grows with the returns).
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
    from jax.flatten_util import ravel_pytree

    import envs
    from mjx_collo import actor as actor_lib
    from mjx_collo import checkpoint, session
    from mjx_collo import replay as replay_lib
    from mjx_collo import world_model as wm_lib
    from mjx_collo.agent import uses_prior
    from mjx_collo.world_model import rssm

    ck = checkpoint.Checkpointer(run, read_only=True)
    _, meta = ck.newest_meta()
    c = ck.config_of(meta)
    if not uses_prior(c):
        raise SystemExit(f"error: {run} has no policy prior (planner.init={c.planner.init})")
    env = envs.from_config(c.env)
    state, _, step = session.restore_state(ck, c, env, meta, replay=True)
    imag = wm_lib.imagination_model(c.wm)

    @jax.jit
    def grads(s, key):
        """The two terms' gradients (flat) on one replay batch, drawn as the learner draws it."""
        k_batch, k_obs, k_a, k_pick = jax.random.split(key, 4)
        batch = replay_lib.sample(s.replay, k_batch, c.replay.batch, c.replay.length)
        post, _ = rssm.observe(c.wm, s.wm, batch["obs"], batch["action"], batch["is_first"], k_obs)
        starts = actor_lib.flatten_starts(post, 2)
        n = jax.tree.leaves(starts)[0].shape[0]
        if 0 < c.actor.starts < n:  # the learner's subset of imagination starts
            pick = jax.random.permutation(k_pick, n)[: c.actor.starts]
            starts = jax.tree.map(lambda x: x[pick], starts)
        starts = jax.lax.stop_gradient(starts)
        feat = jax.lax.stop_gradient(rssm.get_feat(post)[:, :-1])
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
        return ravel_pytree(g_pg)[0], ravel_pytree(g_bc)[0]

    rows = []
    for r in range(meta["num_runs"]):
        s = jax.tree.map(lambda x, r=r: x[r], state)
        g = [grads(s, jax.random.PRNGKey(i)) for i in range(batches)]
        pg_, bc_ = (np.stack([np.asarray(x[j]) for x in g]) for j in (0, 1))
        mpg, mbc = pg_.mean(0), bc_.mean(0)  # the gradients averaged over the batches
        row = {
            "run": r,
            # the norm of the batch-averaged gradient: single-batch norms of the objective's
            # gradient (from actor.starts imagination starts) carry its sampling noise
            "grad_norm_pg": float(np.linalg.norm(mpg)),
            "grad_norm_bc": float(np.linalg.norm(mbc)),
            "ratio": float(np.linalg.norm(mpg) / np.linalg.norm(mbc)),
            "ratio_single_batch": float(
                np.mean(np.linalg.norm(pg_, axis=1) / np.linalg.norm(bc_, axis=1))
            ),
            "cosine": float(mpg @ mbc / (np.linalg.norm(mpg) * np.linalg.norm(mbc))),
        }
        rows.append(row)
        print(
            f"{run.name} ({c.env.task}, {step} env steps) run {r}: |grad pg| "
            f"{row['grad_norm_pg']:.3g}, |grad bc| {row['grad_norm_bc']:.3g}, ratio "
            f"{row['ratio']:.3g} (single batches {row['ratio_single_batch']:.3g}), cosine "
            f"{row['cosine']:.2f} (actor.pg={c.actor.pg:g}, actor.bc={c.actor.bc:g})"
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

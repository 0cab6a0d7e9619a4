"""Where the planner bootstraps, does the value know what it is talking about?

``python benchmarks/probe_value.py --ckpt RUN_DIR [--seed 0] [--fresh 2000] [planner.k=v ...]``

In ``value.mode=replay`` the value is trained on posterior features ``[one-hot sample, h]`` of
replay sequences, against lambda-returns of the real rewards. The planner bootstraps it at
``[prior probabilities m(h), h]`` of an *imagined* state: the end of a plan that was optimised
against that same value. This needs one seed of a checkpoint with its replay and reports:

1. the target value on replay states under the three features of the same states (training's
   sample, posterior probabilities, the planner's prior probabilities) against the lambda-return
   targets: does the value read the planner's features as it reads its own?
2. the planner (as trained, or under ``planner.*`` overrides) from 16 replay posteriors: the model
   reward over the plan and the value at the end of its feasible model rollout.
3. open-loop: from replay posteriors, the model rolls the *logged* actions forward H steps; the
   value and reward heads at those imagined states against the same heads at the real posteriors
   H steps later. A value that is higher on imagined states than on the real states they stand
   for is biased where the planner reads it, whatever the planner does.
4. with ``--fresh N``: a second value trained from a new initialisation for N updates on the same
   replay (world model frozen). Two values that agree on replay states but not at the plan ends
   mean the planner found the first one's errors (the optimiser's curse), not better states.

Prints; writes nothing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--ckpt", required=True, help="run directory or checkpoint step dir")
    p.add_argument("--seed", type=int, default=0, help="which seed of the run")
    p.add_argument("--batch", type=int, default=64, help="replay sequences scored")
    p.add_argument("--fresh", type=int, default=0, help="updates of a second, fresh value")
    p.add_argument("overrides", nargs="*", help="planner.* overrides for part 2")
    args = p.parse_args(argv)

    import jax
    import jax.numpy as jnp
    import numpy as np

    import envs
    from mjx_collo import agent as agent_lib
    from mjx_collo import checkpoint, session
    from mjx_collo import replay as replay_lib
    from mjx_collo import value as value_lib
    from mjx_collo import world_model as wm
    from mjx_collo.planners.protocol import rollout

    session.setup_jax()
    ck = checkpoint.Checkpointer(args.ckpt, read_only=True)
    _, meta = ck.newest_meta()
    cfg0 = ck.config_of(meta)
    if not cfg0.value.enabled or cfg0.planner.kind == "dreamer":
        print("error: the checkpoint has no planner value (value.enabled)", file=sys.stderr)
        return 2
    if not meta.get("has_replay"):
        print("error: the checkpoint has no replay (run.save_replay=false)", file=sys.stderr)
        return 2
    cfg = session.eval_config(cfg0, args.overrides)
    env = envs.from_config(cfg0.env)
    state, _, step = session.restore_state(ck, cfg0, env, meta, replay=True)
    s = jax.tree.map(lambda x: x[args.seed], state)
    rep = s.replay
    vc, wc, length = cfg0.value, cfg0.wm, cfg0.replay.length

    def posteriors(key, batch):
        k_s, k_o = jax.random.split(key)
        b = replay_lib.sample(rep, k_s, batch, length)
        post, _ = wm.observe(wc, s.wm, b["obs"], b["action"], b["is_first"], k_o)
        feat = wm.get_feat(post)
        return post, {
            "feat": feat,
            "reward": b["reward"],
            "is_first": b["is_first"],
            "action": b["action"],
        }

    @jax.jit
    def scored(key, target):
        post, batch = posteriors(key, args.batch)
        feats = {
            "posterior sample (training)": batch["feat"],
            "posterior probabilities": jnp.concatenate(
                [wm.dist_mean(wc, post.stats), post.deter], -1
            ),
            "prior probabilities m(h) (planner)": jnp.concatenate(
                [wm.prior_mean(wc, s.wm, post.deter), post.deter], -1
            ),
        }
        y, mask = value_lib.batch_targets(vc, target, batch)
        vals = {k: value_lib.apply_value(vc, target, f[:, :-1]) for k, f in feats.items()}
        return y, mask, vals, jax.tree.map(lambda x: x[:16, -1], post)

    def report(name, y, mask, v):
        sel = mask > 0
        err = v[sel] - y[sel]
        corr = np.corrcoef(v[sel], y[sel])[0, 1]
        print(
            f"{name:<40} {np.mean(err**2):8.2f} {err.mean():7.2f} {corr:6.3f} {v[sel].mean():7.2f}"
        )

    y, mask, vals, ctxs = jax.device_get(scored(jax.random.PRNGKey(11), s.value.target))
    sel = mask > 0
    print(
        f"{cfg0.method} on {cfg0.env.task}, checkpoint at {step} env steps, seed {args.seed}: "
        f"{int(sel.sum())} replay states, lambda-return target mean {y[sel].mean():.2f} "
        f"(std {y[sel].std():.2f})"
    )
    print(
        f"{'value (target net) on replay states':<40} {'mse':>8} {'bias':>7} {'corr':>6} {'mean':>7}"
    )
    for name, v in vals.items():
        report(name, y, mask, v)

    fresh = None
    if args.fresh:
        fresh = value_lib.init_value(vc, jax.random.PRNGKey(99), wm.feat_size(wc))

        @jax.jit
        def train(vs, key):
            def body(i, vs):
                k1, k2 = jax.random.split(jax.random.fold_in(key, i))
                _, batch = posteriors(k1, cfg0.replay.batch)
                batch = {k: batch[k] for k in ("feat", "reward", "is_first")}
                return value_lib.train_step(vc, vs, jax.lax.stop_gradient(batch), k2)[0]

            return jax.lax.fori_loop(0, args.fresh, body, vs)

        fresh = train(fresh, jax.random.PRNGKey(7))
        y2, mask2, vals2, _ = jax.device_get(scored(jax.random.PRNGKey(11), fresh.target))
        report(
            f"fresh value, {args.fresh} updates (planner feat)",
            y2,
            mask2,
            vals2["prior probabilities m(h) (planner)"],
        )

    agent = agent_lib.make_agent(cfg, int(env.action_size))
    pl, model = agent.planner, agent.model
    pp = wm.plan_params(s.wm, s.value.target, s.actor.params if agent.uses_prior else None)
    horizon = cfg.planner.horizon

    @jax.jit
    def open_loop(key):
        post, batch = posteriors(key, args.batch)
        first = jnp.any(batch["is_first"][:, 1 : horizon + 1], axis=1)  # crosses an episode start

        def one(i):
            # action[t] is a_{t-1}, the one that led into obs_t: states 1..H follow actions 1..H
            ctx = jax.tree.map(lambda x: x[i, 0], post)
            zs = rollout(model, pp, ctx, batch["action"][i, 1 : horizon + 1])
            f_img = jnp.concatenate([wm.prior_mean(wc, s.wm, zs[-1]), zs[-1]], -1)
            r_img = jax.vmap(model.reward, in_axes=(None, 0))(pp, zs)
            return value_lib.apply_value(vc, s.value.target, f_img), jnp.sum(r_img)

        v_img, r_img = jax.vmap(one)(jnp.arange(args.batch))
        f_real = batch["feat"][:, horizon]
        v_real = value_lib.apply_value(vc, s.value.target, f_real)
        r_real = jnp.sum(batch["reward"][:, 1 : horizon + 1], axis=1)
        return v_img, v_real, r_img, r_real, ~first

    v_img, v_real, r_img, r_real, ok = jax.device_get(open_loop(jax.random.PRNGKey(13)))
    dv, dr = (v_img - v_real)[ok], (r_img - r_real)[ok]
    print(
        f"open loop, logged actions, {horizon} steps ({int(ok.sum())} sequences): value at the "
        f"imagined end {v_img[ok].mean():.2f} vs at the real one {v_real[ok].mean():.2f} "
        f"(bias {dv.mean():+.2f}, rmse {np.sqrt(np.mean(dv**2)):.2f}); reward sum imagined "
        f"{r_img[ok].mean():.2f} vs real {r_real[ok].mean():.2f} (rmse {np.sqrt(np.mean(dr**2)):.2f})"
    )

    @jax.jit
    def plan(ctx, key):
        k1, k2 = jax.random.split(key)
        out, _, _ = pl.optimize(pp, ctx, pl.init(pp, ctx, k1), k2)
        zs = rollout(model, pp, ctx, jnp.clip(pl.actions(out), -1.0, 1.0))
        rew = jnp.sum(jax.vmap(model.reward, in_axes=(None, 0))(pp, zs))
        feat_end = jnp.concatenate([wm.prior_mean(wc, s.wm, zs[-1]), zs[-1]], -1)
        ends = [value_lib.apply_value(vc, s.value.target, feat_end)]
        if fresh is not None:
            ends.append(value_lib.apply_value(vc, fresh.target, feat_end))
        return rew, jnp.stack(ends), value_lib.apply_value(vc, s.value.target, wm.get_feat(ctx))

    pk = jax.random.split(jax.random.PRNGKey(5), 16)
    rew, v_end, v_start = jax.device_get(jax.vmap(plan)(ctxs, pk))
    h, g = cfg.planner.horizon, cfg.planner.gamma
    print(
        f"planner {cfg.planner.kind} ({' '.join(args.overrides) or 'as trained'}), 16 contexts: "
        f"model reward over the plan {rew.mean():.2f}, value at the start {v_start.mean():.2f}, "
        f"value at the plan's end {v_end[:, 0].mean():.2f} (x gamma^H: {g**h * v_end[:, 0].mean():.2f})"
    )
    if fresh is not None:
        d = v_end[:, 0] - v_end[:, 1]
        print(
            f"  fresh value at the same plan ends {v_end[:, 1].mean():.2f}: the trained one is "
            f"higher by {d.mean():.2f} +- {d.std():.2f} (per context)"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())

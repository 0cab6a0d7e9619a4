"""Why does reacher_easy plateau? Reaching diagnostics of a trained checkpoint.

``python benchmarks/probe_reacher.py --ckpt RUN_DIR --seed 0 --episodes 6 [planner.k=v ...]``

Runs deterministic episodes (as ``make eval`` does) with one seed of a reacher checkpoint, under
optional ``planner.*`` overrides, and records per episode: the return, the finger-to-target distance
at the start, its minimum, the first agent step with reward, and the value of the posterior at the
start and the end. The task pays reward only inside ``target + finger radius`` (0.06 on
reacher_easy), so these separate "never goes near the target" (a model / value problem: the agent
does not know the target pays) from "gets near but cannot stay" (a control-precision problem: e.g.
too many actions executed open-loop). It also scores the reward head on the posterior of every
visited state against the reward the env paid on arriving there (MSE, mean prediction per paid
reward and per finger-to-target distance band): the planner can only chase reward the head sees.
Appends a row to ``bench_results/reacher_probe.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--ckpt", required=True, help="reacher run directory or checkpoint step dir")
    p.add_argument("--seed", type=int, default=0, help="which seed of the run")
    p.add_argument("--episodes", type=int, default=6)
    p.add_argument("--out", default=str(ROOT / "bench_results" / "reacher_probe.json"))
    p.add_argument("overrides", nargs="*", help="planner.* overrides, as for make eval")
    args = p.parse_args(argv)

    import jax
    import jax.numpy as jnp
    import numpy as np

    import envs
    from mjx_collo import agent as agent_lib
    from mjx_collo import checkpoint, session
    from mjx_collo import value as value_lib
    from mjx_collo import world_model as wm_lib

    session.setup_jax()
    ck = checkpoint.Checkpointer(args.ckpt, read_only=True)
    _, meta = ck.newest_meta()
    cfg0 = ck.config_of(meta)
    if not cfg0.env.task.startswith("reacher"):
        print(f"error: {cfg0.env.task} is not a reacher task", file=sys.stderr)
        return 2
    cfg = session.eval_config(cfg0, args.overrides)
    env = envs.from_config(cfg.env)
    state, _, step = session.restore_state(ck, cfg0, env, meta)
    s = jax.tree.map(lambda x: x[args.seed], state)
    agent = agent_lib.make_agent(cfg, int(env.action_size))
    n, length = args.episodes, cfg.env.episode_env_steps // cfg.env.action_repeat
    reduced = wm_lib.latent_model(cfg.wm, "reduced")

    @jax.jit
    def episodes(s, key):
        k_env, k_carry, key = jax.random.split(key, 3)
        es = jax.vmap(env.reset)(jax.random.split(k_env, n))
        prior = s.actor.params if agent.uses_prior else None  # the default plans from its prior
        params = wm_lib.plan_params(s.wm, s.value.target if s.value is not None else None, prior)
        carry = agent_lib.init_carry(agent, params, n, k_carry)

        def step_fn(c, t):
            es, carry = c
            k_obs, k_plan, k_act = jax.random.split(jax.random.fold_in(key, t), 3)
            first = jnp.broadcast_to(t == 0, (n,))
            carry = agent_lib.observe(agent, s.wm, carry, es.obs, first, k_obs)
            carry = jax.lax.cond(
                t % agent.cache_len == 0,
                lambda cr: agent_lib.replan(agent, params, cr, k_plan)[0],
                lambda cr: cr,
                carry,
            )
            feat = wm_lib.get_feat(carry.post)
            v = (
                value_lib.apply_value(cfg.value, s.value.target, feat)
                if s.value is not None
                else jnp.zeros((n,))
            )
            r_pred = wm_lib.reward(cfg.wm, s.wm, feat)  # reward of arriving in this state
            # ... and as the planner sees this state (reduced space: [prior probabilities of h, h])
            r_plan = reduced.reward(wm_lib.plan_params(s.wm), carry.post.deter)
            a, carry = agent_lib.act(agent, None, carry, k_act, training=False)
            es = jax.vmap(env.step)(es, a)
            obs = es.info.get("state_obs", es.obs)  # the state vector, pixel runs included
            dist = jnp.linalg.norm(obs[:, 2:4], axis=-1)  # obs: position 2, to_target 2, velocity 2
            return (es, carry), (es.reward, dist, v, r_pred, r_plan)

        _, out = jax.lax.scan(step_fn, (es, carry), jnp.arange(length))
        return out

    t0 = time.perf_counter()
    r, d, v, rp, rpl = (np.asarray(x) for x in jax.device_get(episodes(s, jax.random.PRNGKey(123))))
    secs = time.perf_counter() - t0
    rows = []
    for i in range(n):
        hit = np.nonzero(r[:, i] > 0)[0]
        rows.append(
            {
                "return": float(r[:, i].sum()),
                "dist_start": float(d[0, i]),
                "dist_min": float(d[:, i].min()),
                "first_reward_step": int(hit[0]) if len(hit) else None,
                "value_start": float(v[1, i]),
                "value_end": float(v[-1, i]),
            }
        )
        print(
            f"episode {i}: return {rows[-1]['return']:6.1f}  distance start {d[0, i]:.3f} "
            f"min {d[:, i].min():.3f}  first reward at step {hit[0] if len(hit) else '-'}  "
            f"V start {v[1, i]:.1f} end {v[-1, i]:.1f}"
        )
    mean = float(r.sum(0).mean())
    print(f"mean return {mean:.1f} over {n} episodes ({secs:.0f}s incl. compile)")
    # Reward head on the posterior of the state the env reward was received on arriving in:
    # the reward of step t pairs with the posterior filtered from the observation after it.
    true, pred, plan = r[:-1].ravel(), rp[1:].ravel(), rpl[1:].ravel()
    head = {
        "mse": float(np.mean((pred - true) ** 2)),
        "mse_plan_features": float(np.mean((plan - true) ** 2)),
    }
    for lo, hi, name in ((-0.5, 0.5, "0"), (0.5, 1.5, "1"), (1.5, 2.5, "2")):
        sel = (true > lo) & (true < hi)
        if sel.any():
            head[f"pred_when_{name}"] = float(pred[sel].mean())
            head[f"steps_{name}"] = int(sel.sum())
    # ... and against the finger-to-target distance of that state (the task pays inside 0.06).
    dist = d[:-1].ravel()
    for lo, hi in ((0.0, 0.06), (0.06, 0.1), (0.1, 0.2), (0.2, 1.0)):
        sel = (dist >= lo) & (dist < hi)
        if sel.any():
            head[f"pred_at_dist_{lo}-{hi}"] = float(pred[sel].mean())
            head[f"plan_pred_at_dist_{lo}-{hi}"] = float(plan[sel].mean())
            head[f"true_at_dist_{lo}-{hi}"] = float(true[sel].mean())
    print("reward head: " + ", ".join(f"{k} {v:.3g}" for k, v in head.items()))
    out = Path(args.out)
    results = json.loads(out.read_text()) if out.exists() else []
    results.append(
        {
            "ckpt": str(args.ckpt),
            "env_steps": step,
            "seed": args.seed,
            "overrides": args.overrides,
            "mean_return": mean,
            "episodes": rows,
            "reward_head": head,
        }
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Why does quadruped_walk plateau near 150? Getting up, measured four ways.

``python benchmarks/probe_quadruped.py RUN_DIR [RUN_DIR ...]`` (quadruped run directories with a
checkpoint that holds the replay; ``make study``'s cells do)

dm_control's quadruped starts each episode in a uniformly random orientation, so about three
starts in four land on the back or side, where the task pays almost nothing (its upright factor
is 0 upside down). An agent that walks only from the starts that land on their feet scores about
a quarter of its walking return. The probe separates "cannot walk" from "cannot get up":

1. physics: from random starts that land down, how often colored-noise actions get the body up
   and how often the physics goes unstable, per MjModel option set (native MuJoCo,
   envs.quadruped.get_up_trials). dm_control's options: never; faithful options must agree;
   1b. exploration: with dm_control's options, how far random actions of each kind (the
   training noise around a still plan, white / pink / red noise at full scale and at 0.3 and 0.6
   per step -- explore.color's noise --, uniform actions held for k steps) roll the body from a down start: how many reach their side (upright > 0) or
   their feet, and the mean upright factor of the reward over the episode;
2. training data: in each run's replay (newest checkpoint), the episodes that started down
   (torso upright < 0.5 at the first step), those that reached a side (upright > 0 once landed) and
   those that ended up (mean upright > 0.8 over the last 100 agent steps) -- a world model cannot predict getting up from data that never shows it;
3. planning with a perfect model: CEM on the true simulator from the back, white against
   temporally correlated action samples (how findable getting up is, given the model);
4. evaluations: each logged evaluation's starts are re-drawn from the run's keys (as
   runner.start_evaluation and rollout.episodes draw them) and the logged mean return is split by
   least squares into a return per start that lands on its feet and per start that does not;
5. model and value on the episodes that started on their feet (replay, newest checkpoint): from 5
   filtered steps, the world model's open-loop prediction over the planner's horizon of the torso
   upright and the reward under the actions the agent executed, against what happened (does the
   model know that these actions flip the body?), and the value of the posterior when upright and
   on its back against the discounted return the agent got from there.

Writes ``bench_results/quadruped_probe.json`` (one entry per run directory).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# a start "on its feet" and an episode that ended up: the classes every evaluation logs
from envs.quadruped import ENDED_UP, ENDED_UP_STEPS  # noqa: E402
from envs.quadruped import START_ON_FEET as UP  # noqa: E402


def physics_check(starts: int) -> dict:
    """Getting up under pink-noise actions (envs.quadruped.get_up_trials) with dm_control's options,
    the tuned options, and the tuned options chosen until 2026-12-06 (2 / 4, eulerdamp off)."""
    from envs import base, quadruped

    floor = quadruped.DEFAULT_TIME_LIMIT * quadruped.WALK_SPEED
    old = quadruped.build_model("tuned", floor)
    base.tune_solver(old, 2, 4, eulerdamp=False)
    models = {
        "dmc": quadruped.build_model("dmc", floor),
        "tuned": quadruped.build_model("tuned", floor),
        "tuned until 2026-12-06 (2 / 4, eulerdamp off)": old,
    }
    out = {}
    for name, m in models.items():
        for beta in (1.0, 2.0):
            up, unstable = quadruped.get_up_trials(m, starts, beta)
            out[f"{name}, beta {beta:g}"] = {"starts": starts, "got_up": up, "unstable": unstable}
            print(
                f"physics {name}, colored noise beta {beta:g}: got up from {up} of {starts} "
                f"down starts, {unstable} unstable"
            )
    return out


def exploration_reach(starts: int, seed: int = 0) -> dict:
    """How far random actions roll the quadruped off its back (dm_control's options, native
    MuJoCo, 500 agent steps of 2 control steps from down starts as get_up_trials draws them).
    An agent's world model can predict only what such exploration shows it."""
    import mujoco
    import numpy as np

    from envs import quadruped

    m = quadruped.build_model("dmc", quadruped.DEFAULT_TIME_LIMIT * quadruped.WALK_SPEED)
    d = mujoco.MjData(m)
    torso = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "torso")
    substeps = round(quadruped.CONTROL_DT / m.opt.timestep)

    def actions(rng, kind: str) -> np.ndarray:
        if kind == "gaussian 0.3 (training noise around a still plan)":
            return np.clip(0.3 * rng.normal(size=(500, m.nu)), -1, 1)
        if kind.startswith("colored"):  # "colored beta 2" (full scale) or "colored beta 2 x0.3"
            words = kind.split()
            scale = float(words[3][1:]) if len(words) > 3 else 1.0
            beta = float(words[2])
            return np.clip(scale * quadruped.colored_noise(rng, beta, 500, m.nu), -1, 1)
        hold = int(kind.split()[-1])  # "uniform held k": piecewise constant uniform actions
        return np.repeat(rng.uniform(-1, 1, (500 // hold + 1, m.nu)), hold, 0)[:500]

    kinds = ["gaussian 0.3 (training noise around a still plan)"]
    kinds += [f"colored beta {b:g}" for b in (0.0, 1.0, 2.0)]
    # explore.color's noise at the training scale (explore.noise 0.3 per step) and twice it
    kinds += [f"colored beta {b:g} x{x:g}" for x in (0.3, 0.6) for b in (0.0, 1.0, 2.0)]
    kinds += [f"uniform held {k}" for k in (5, 10, 25)]
    out = {}
    for kind in kinds:
        rng = np.random.default_rng(seed)
        side = feet = done = 0
        factor = []
        while done < starts:
            upright = quadruped.random_drop(m, d, rng)
            a = actions(rng, kind)
            if upright >= UP:
                continue
            done += 1
            ups = []
            for k in range(500):
                d.ctrl[:] = a[k]
                mujoco.mj_step(m, d, nstep=2 * substeps)
                ups.append(d.xmat[torso][8])
            settled = np.array(ups[25:])  # after the drop has landed
            side += int(settled.max() > 0.0)
            feet += int(settled.max() > UP)
            factor.append(float(np.mean((settled + 1) / 2)))
        out[kind] = {
            "starts": starts,
            "reached_side": side,
            "reached_feet": feet,
            "mean_upright_factor": float(np.mean(factor)),
        }
        print(
            f"exploration {kind}: {side} of {starts} down starts reach their side, {feet} their "
            f"feet; mean upright factor {np.mean(factor):.3f}",
            flush=True,
        )
    return out


def perfect_model_cem(hold: int, samples: int = 200, iters: int = 30, seed: int = 0) -> list:
    """CEM on the true simulator (dm_control's options, native MuJoCo) from the settled back pose:
    150 control steps (3 s) of actions held for ``hold`` steps each, scored by the mean torso
    upright over the last second; elites 10%, std floor 0.05. How findable getting up is for a
    planner with a perfect model, with white (hold 1) against correlated (hold 10) samples.
    Returns the best score per iteration."""
    import mujoco
    import numpy as np

    from envs import quadruped

    m = quadruped.build_model("dmc", quadruped.DEFAULT_TIME_LIMIT * quadruped.WALK_SPEED)
    d = mujoco.MjData(m)
    torso = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "torso")
    sub = round(quadruped.CONTROL_DT / m.opt.timestep)
    d.qpos[3:7] = [0, 1, 0, 0]  # upside down, dropped and settled for 2 s
    d.qpos[2] = 0.6
    mujoco.mj_step(m, d, nstep=100 * sub)
    start = mujoco.MjData(m)
    mujoco.mj_copyData(start, m, d)
    steps, blocks = 150, 150 // hold

    def score(a):
        mujoco.mj_copyData(d, m, start)
        ups = []
        for k in range(steps):
            d.ctrl[:] = a[k // hold]
            mujoco.mj_step(m, d, nstep=sub)
            ups.append(d.xmat[torso][8])
        return float(np.mean(ups[-50:]))

    rng = np.random.default_rng(seed)
    mu, sd = np.zeros((blocks, m.nu)), np.ones((blocks, m.nu))
    best = []
    for _ in range(iters):
        a = np.clip(mu + sd * rng.normal(size=(samples, blocks, m.nu)), -1, 1)
        sc = np.array([score(x) for x in a])
        elites = a[np.argsort(sc)[-samples // 10 :]]
        mu, sd = elites.mean(0), elites.std(0) + 0.05
        best.append(float(sc.max()))
    print(
        f"perfect-model CEM, actions held {hold} step(s), {samples} samples: best mean upright "
        f"over the last second {best[0]:+.2f} after 1 iteration, {best[iters // 2 - 1]:+.2f} after "
        f"{iters // 2}, {best[-1]:+.2f} after {iters} (-1 on the back, 0 on the side, 1 upright)"
    )
    return best


def model_check(cfg, state, ui: int, filtered: int = 5) -> list[dict]:
    """Part 5, per run. For each replay episode that started on its feet (after the prefill), the
    model filters ``filtered`` steps, then predicts the planner's horizon open loop under the
    executed actions, deterministically (latent means, as the planner rolls out); an episode
    flipped (really / by the model) when its upright over the window's last 10 steps averages < 0.
    And the value (target network) on the posteriors of agent steps 50-150 of the run's second
    half of episodes, against the discounted return the agent really got from there (its own
    behaviour, which is what a value learns), split by the real upright (> 0.8 / < -0.8)."""
    import jax
    import numpy as np

    from mjx_collo import value as value_lib
    from mjx_collo.world_model import heads, rssm

    k, h, wm, gamma = filtered, cfg.planner.horizon, cfg.wm, cfg.value.gamma
    prefill = cfg.run.prefill // cfg.env.episode_env_steps  # episodes of random actions

    @jax.jit
    def predict(params, obs, act, first, key):  # rows hold obs_t and action_{t-1}
        post, _ = rssm.observe(wm, params, obs[None, :k], act[None, :k], first[None, :k], key)
        start = jax.tree.map(lambda x: x[0, k - 1], post)

        def step(z, a):
            z = rssm.img_step_mean(wm, params, z, a)
            return z, rssm.get_feat(z)

        feat = jax.lax.scan(step, start, act[k : k + h])[1]
        return heads.predict_obs(wm, params, feat)[:, ui], heads.reward(wm, params, feat)

    @jax.jit
    def values(params, vparams, obs, act, first, key):
        post, _ = rssm.observe(wm, params, obs[None], act[None], first[None], key)
        return value_lib.apply_value(cfg.value, vparams, rssm.get_feat(post))[0]

    data = {f: np.asarray(state.replay.data[f])[:, :, 0] for f in ("obs", "action", "reward")}
    data["is_first"] = np.asarray(state.replay.data["is_first"])[:, :, 0]
    count = np.broadcast_to(np.asarray(state.replay.count), (data["obs"].shape[0],))
    key = jax.random.PRNGKey(0)
    at = [9, 19, h - 1]  # agent steps after the filtered ones, the last at the horizon
    out = []
    for s in range(data["obs"].shape[0]):
        params = jax.tree.map(lambda x, s=s: x[s], state.wm)
        vparams = jax.tree.map(lambda x, s=s: x[s], state.value.target)
        obs, act = data["obs"][s, : count[s]], data["action"][s, : count[s]]
        rew, first = data["reward"][s, : count[s]], data["is_first"][s, : count[s]]
        starts = np.flatnonzero(first)
        ends = [*starts[1:], count[s]]
        eps = []
        value = {"upright": ([], []), "on_back": ([], [])}  # (value, discounted return got)
        for i, (a, e) in enumerate(zip(starts, ends, strict=True)):
            if i >= len(starts) // 2 and e - a >= 300:
                v = np.asarray(values(params, vparams, obs[a:e], act[a:e], first[a:e], key))
                r = rew[a + 1 : e]  # the reward of arriving at row t + 1 follows state t
                ret = np.zeros(len(r) + 1)
                for t in range(len(r) - 1, -1, -1):
                    ret[t] = r[t] + gamma * ret[t + 1]
                for t in range(50, 150):
                    u = obs[a + t, ui]
                    cls = "upright" if u > 0.8 else "on_back" if u < -0.8 else None
                    if cls:
                        value[cls][0].append(v[t])
                        value[cls][1].append(ret[t])
            if e - a < k + h or obs[a, ui] < UP or i < prefill:
                continue
            seg = slice(a, a + k + h)
            pu, pr = (np.asarray(x) for x in predict(params, obs[seg], act[seg], first[seg], key))
            real = obs[a + k : a + k + h, ui]
            rr = rew[a + k : a + k + h]  # rows k.. hold the rewards of arriving at obs_k..
            eps.append(
                (real[-10:].mean() < 0, pu[-10:].mean() < 0, real[at], pu[at], rr.sum(), pr.sum())
            )
        entry = {"run": s, "horizon": h}
        for cls, (v, g) in value.items():
            entry[f"value_{cls}"] = float(np.mean(v)) if v else None
            entry[f"return_got_{cls}"] = float(np.mean(g)) if g else None
            entry[f"states_{cls}"] = len(v)
        for tag, real_flip in (("flipped", True), ("stayed", False)):
            r = [x for x in eps if x[0] == real_flip]
            entry[tag] = {
                "episodes": len(r),
                "predicted_flipped": int(sum(x[1] for x in r)),
                f"upright_at_{'_'.join(str(t + 1) for t in at)}_real": (
                    np.mean([x[2] for x in r], 0).astype(float).round(2).tolist() if r else None
                ),
                f"upright_at_{'_'.join(str(t + 1) for t in at)}_predicted": (
                    np.mean([x[3] for x in r], 0).astype(float).round(2).tolist() if r else None
                ),
                "reward_real": float(np.mean([x[4] for x in r])) if r else None,
                "reward_predicted": float(np.mean([x[5] for x in r])) if r else None,
            }
            if r:
                e = entry[tag]
                print(
                    f"  run {s}, {len(r)} on-feet episodes that {tag} within {k + h} agent steps: "
                    f"{e['predicted_flipped']} predicted to flip; upright at "
                    f"+{'/+'.join(str(t + 1) for t in at)} real "
                    f"{np.mean([x[2] for x in r], 0).astype(float).round(2).tolist()}, predicted "
                    f"{np.mean([x[3] for x in r], 0).astype(float).round(2).tolist()}; reward over {h} steps "
                    f"real {e['reward_real']:.1f}, predicted {e['reward_predicted']:.1f}"
                )
        said = [
            f"{name} {entry[f'value_{cls}']:.1f} (return got {entry[f'return_got_{cls}']:.1f}, "
            f"{entry[f'states_{cls}']} states)"
            if entry[f"states_{cls}"]
            else f"{name}: no states"  # a run whose late episodes never stood (or lay) there
            for cls, name in (("upright", "upright"), ("on_back", "on its back"))
        ]
        print(f"  run {s}: value " + ", ".join(said))
        out.append(entry)
    return out


def probe_run(run: Path) -> dict:
    import jax
    import mujoco
    import numpy as np

    import envs
    from mjx_collo import checkpoint, parallel, session

    ck = checkpoint.Checkpointer(run, read_only=True)
    _, meta = ck.newest_meta()
    cfg = ck.config_of(meta)
    env = envs.from_config(cfg.env)
    base = env.unwrapped
    if not hasattr(base, "_hinge_q"):
        raise SystemExit(f"error: {run} is a {cfg.env.task} run; the probe reads quadruped runs")
    state, keys, step = session.restore_state(ck, cfg, env, meta, replay=True)
    # the observation's torso-upright entry: ego (hinge q, hinge v, act), velocimeter (3), upright
    ui = len(base._hinge_q) + len(base._hinge_v) + base.mj_model.na + 3
    obs = np.asarray(state.replay.data["obs"])[:, :, 0, ui]  # [runs, rows]
    first = np.asarray(state.replay.data["is_first"])[:, :, 0]
    count = np.broadcast_to(np.asarray(state.replay.count), (obs.shape[0],))
    training = []
    for s in range(obs.shape[0]):
        up, f = obs[s, : count[s]], np.flatnonzero(first[s, : count[s]])
        eps = [up[a:b] for a, b in zip(f, [*f[1:], count[s]], strict=True) if b - a > 400]
        down = [u for u in eps if u[0] < UP]
        got_up = sum(u[-ENDED_UP_STEPS:].mean() > ENDED_UP for u in down)
        side = sum(u[25:].max() > 0.0 for u in down)  # rolled at least onto a side, once landed
        on_feet = [u for u in eps if u[0] >= UP]
        fell = sum(u[-ENDED_UP_STEPS:].mean() <= ENDED_UP for u in on_feet)
        training.append(
            {
                "episodes": len(eps),
                "started_down": len(down),
                "got_up": int(got_up),
                "reached_side": int(side),
                "started_on_feet": len(on_feet),
                "ended_down": int(fell),
            }
        )
        print(
            f"{run.name} run {s} replay ({step} env steps): {len(eps)} episodes, "
            f"{len(down)} started down, {side} of them reached a side, {got_up} got up; "
            f"{len(on_feet)} started on their feet, {fell} of them ended down"
        )

    model = model_check(cfg, state, ui)

    torso = mujoco.mj_name2id(base.mj_model, mujoco.mjtObj.mjOBJ_BODY, "torso")
    n = cfg.run.eval_episodes
    seed_keys = parallel.seed_keys(cfg, meta["num_runs"], parallel.first_seed(meta["labels"]))

    @jax.jit
    def starts(key):  # rollout.episodes: k_env, k_carry, key = split(key, 3)
        k_env = jax.random.split(key, 3)[0]
        st = jax.vmap(env.reset)(jax.random.split(k_env, n))
        return st.pipeline_state.xmat[:, torso, 2, 2]

    rows = []
    for line in (run / "metrics.jsonl").read_text().splitlines():
        r = json.loads(line)
        if r.get("kind") == "eval" and "eval/return" in r:
            u = np.asarray(starts(jax.random.fold_in(seed_keys[r["seed"]], r["step"])))
            rows.append(
                {
                    "step": r["step"],
                    "seed": r["seed"],
                    "mean_return": r["eval/return"],
                    "starts_on_feet": int((u >= UP).sum()),
                    "start_upright": np.round(u, 3).tolist(),
                }
            )
    k = np.array([r["starts_on_feet"] for r in rows], float)
    total = np.array([r["mean_return"] for r in rows]) * n  # summed over the episodes
    a = np.stack([k, n - k], 1)  # total = k * R_feet + (n - k) * R_down
    (r_feet, r_down), *_ = np.linalg.lstsq(a, total, rcond=None)
    resid = total - a @ np.array([r_feet, r_down])
    r2 = 1 - (resid**2).sum() / ((total - total.mean()) ** 2).sum()
    print(
        f"{run.name}, {len(rows)} evaluations of {n} episodes: return per start on its feet "
        f"{r_feet:.0f}, per start down {r_down:.0f} (least squares, R^2 {r2:.2f}); "
        f"starts on their feet: {int(k.sum())} of {int(n * len(rows))}"
    )
    by_step: dict[int, list] = {}
    for r in rows:
        by_step.setdefault(r["step"], []).append(r)
    for st, rs in sorted(by_step.items()):
        print(
            f"  {st:>6d}: mean return {np.mean([r['mean_return'] for r in rs]):6.1f}, "
            f"starts on their feet {sum(r['starts_on_feet'] for r in rs)}/{n * len(rs)}"
        )
    return {
        "run": str(run),
        "task": cfg.env.task,
        "method": cfg.method,
        "checkpoint_env_steps": int(step),
        "training": training,
        "model": model,
        "eval_return_per_start_on_feet": float(r_feet),
        "eval_return_per_start_down": float(r_down),
        "eval_fit_r2": float(r2),
        "evaluations": rows,
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("runs", nargs="*", help="quadruped run directories (none: parts 1 and 3 only)")
    p.add_argument("--starts", type=int, default=60, help="down starts per physics check")
    p.add_argument("--out", default=str(ROOT / "bench_results" / "quadruped_probe.json"))
    p.add_argument(
        "--only",
        choices=["exploration", "runs"],
        help="run part 1b alone, or parts 2 and 4 on the given runs alone, and replace only that "
        "entry in --out (seconds, not minutes)",
    )
    args = p.parse_args(argv)
    if args.only == "runs" and not args.runs:
        p.error("--only runs needs quadruped run directories to probe")

    from mjx_collo import session

    session.setup_jax()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)  # a new --out folder, before the work
    if args.only:
        result = json.loads(out.read_text()) if out.exists() else {}
        if args.only == "exploration":
            result["exploration"] = exploration_reach(args.starts)
        else:
            result["runs"] = [probe_run(Path(run)) for run in args.runs]
        out.write_text(json.dumps(result, indent=1))
        print(f"wrote {args.out}")
        return 0
    result = {"physics": physics_check(args.starts), "runs": []}
    result["exploration"] = exploration_reach(args.starts)
    result["perfect_model_cem"] = {f"hold {h}": perfect_model_cem(h) for h in (1, 10)}
    for run in args.runs:
        result["runs"].append(probe_run(Path(run)))
    out.write_text(json.dumps(result, indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    from mjx_collo import xla_log_filter

    xla_log_filter.install()
    sys.exit(main())

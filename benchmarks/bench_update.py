"""What one training update costs, by config: the real learner's ``update`` (world model, value,
and the policy prior's imagination when the config has one), one seed, cheetah, random weights,
jitted, 20 calls per config interleaved so that a busy machine slows every row alike.

Usage: ``python benchmarks/bench_update.py [0,2,...]`` (indices of the cases below; default all).
Prints best and median ms per update. Why: on 2 cores the updates, not the planning FLOPs, set a
run's wall time once the policy prior shrinks the search (docs/EXPERIMENTS.md, issue 39).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402

import envs  # noqa: E402
from mjx_collo import agent as agent_lib  # noqa: E402
from mjx_collo import config  # noqa: E402
from mjx_collo.learner import make_learner  # noqa: E402
from mjx_collo.trainer import make_train  # noqa: E402

_LEAN = [
    "planner.init=policy_cem",
    "actor.starts=64",
    "planner.iters=10",
    "planner.init_cem.iters=3",
    "wm.reward_head=twohot",
    "wm.loss_scales.reward=10",
]
# The rows were measured while the default still had the CEM start and batch 16 (before
# 2026-12-07): PREVIOUS pins those values, so each row keeps its meaning. Today's default is
# "lean, batch 8, 32 starts".
PREVIOUS = [
    "planner.init=cem",
    "actor.starts=0",
    "planner.iters=50",
    "planner.init_cem.iters=6",
    "run.train_steps=100",
    "replay.batch=16",
    "wm.reward_head=mse",
    "wm.loss_scales.reward=1",
]
LEAN = PREVIOUS + _LEAN  # later overrides win
CASES = {
    "default (cem start, value on replay)": PREVIOUS,
    "lean (prior, 64 starts)": LEAN,
    "lean, batch 32": LEAN + ["replay.batch=32"],
    "lean, batch 32 x length 25": LEAN + ["replay.batch=32", "replay.length=25"],
    "lean, 32 starts": LEAN + ["actor.starts=32"],
    "lean, actor horizon 10": LEAN + ["actor.horizon=10"],
    # half the replayed steps (and starts) per update: twice the updates at lean_u100's data rate
    "lean, batch 8, 32 starts": LEAN + ["actor.starts=32", "replay.batch=8"],
    "lean, batch 8": LEAN + ["replay.batch=8"],
}
REPS = 20


def compiled_update(overrides: list[str]):
    """The learner's update for cheetah under ``overrides``, compiled, and a state to run it on."""
    cfg = config.load(task="cheetah_run", method="collodreamer", overrides=overrides)
    env = envs.from_config(cfg.env)
    action_dim = int(env.action_size)
    obs_shape = tuple(jax.eval_shape(env.reset, jax.random.PRNGKey(0)).obs.shape)
    agent = agent_lib.make_agent(cfg, action_dim)
    learner = make_learner(cfg, obs_shape, action_dim, lambda hyper: (cfg, agent))
    state = jax.jit(make_train(cfg, env).init)(jax.random.key(0), {})
    fn = jax.jit(learner.update).lower(state, jax.random.key(1)).compile()
    jax.block_until_ready(fn(state, jax.random.key(1))[0].wm)  # warm-up
    return fn, state


def main() -> None:
    cases = CASES
    if len(sys.argv) > 1:
        pick = set(sys.argv[1].split(","))
        cases = {k: v for i, (k, v) in enumerate(CASES.items()) if str(i) in pick}
    fns = {}
    for name, overrides in cases.items():
        t = time.perf_counter()
        fns[name] = compiled_update(overrides)
        print(f"{name}: compile {time.perf_counter() - t:.1f}s", flush=True)
    times: dict[str, list[float]] = {k: [] for k in fns}
    for rep in range(REPS):
        for name, (fn, state) in fns.items():
            t = time.perf_counter()
            jax.block_until_ready(fn(state, jax.random.key(rep))[0].wm)
            times[name].append(time.perf_counter() - t)
    for name, ts in times.items():
        ts.sort()
        print(f"{name:40s} best {1e3 * ts[0]:6.1f} ms  median {1e3 * ts[len(ts) // 2]:6.1f} ms")


if __name__ == "__main__":
    main()

"""Does the reward head read the planner's latents as well as the ones it was trained on?

``python benchmarks/probe_plan_features.py [--fixture benchmarks/fixtures/cheetah_cem_20k.npz]``

The categorical RSSM trains its reward head on features ``[one-hot posterior sample, h]``. The
reduced-space collocation planner feeds it ``[prior probabilities m(h), h]`` instead (soft
probabilities: samples or argmax have no gradient; docs/ALGORITHM.md pitfall 5). If the head did not
generalise to soft inputs, plans would optimise a reward the model never learned. This filters the
fixture's replay rows with its world model and compares the reward head's error against the logged
rewards under the three features of the same states. Prints a table; writes nothing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
FIXTURE = ROOT / "benchmarks" / "fixtures" / "cheetah_cem_20k.npz"

from mjx_collo import config  # noqa: E402
from mjx_collo import world_model as wm  # noqa: E402
from mjx_collo.plan_quality import load_params, posteriors  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--fixture", type=Path, default=FIXTURE)
    args = p.parse_args(argv)
    cfg = config.load(task="cheetah_run", method="cem")
    params, rep = load_params(cfg, args.fixture)

    posts = posteriors(cfg, params, rep)
    reward = np.asarray(rep["reward"])
    prior = wm.prior_mean(cfg.wm, params, posts.deter)
    feats = {
        "posterior sample (training)": wm.get_feat(posts),
        "posterior probabilities": jnp.concatenate(
            [wm.dist_mean(cfg.wm, posts.stats), posts.deter], -1
        ),
        "prior probabilities m(h) (planner)": jnp.concatenate([prior, posts.deter], -1),
    }
    print(f"{len(reward)} replay rows, true mean reward {reward.mean():.3f}")
    print(f"{'feature':<36} {'reward mse':>10} {'corr':>6} {'mean pred':>9}")
    for name, f in feats.items():
        pred = np.asarray(wm.reward(cfg.wm, params, f))
        mse = np.mean((pred - reward) ** 2)
        corr = np.corrcoef(pred, reward)[0, 1]
        print(f"{name:<36} {mse:10.4f} {corr:6.3f} {pred.mean():9.3f}")
    probs = np.asarray(prior).reshape(len(reward), cfg.wm.stoch, cfg.wm.classes)
    ent = -np.sum(probs * np.log(probs + 1e-8), -1).mean()
    print(f"prior entropy per group: {ent:.2f} nats (uniform: {np.log(cfg.wm.classes):.2f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

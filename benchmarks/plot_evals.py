"""Grouped bar chart of ``make eval`` results: the same checkpoints under several planner settings.

``python benchmarks/plot_evals.py OUT.png GROUP/LABEL=eval.json ... [--title T]``

Each bar is the mean over a JSON's episodes (all runs), with its episodes drawn as dots; bars of the
same GROUP (e.g. a checkpoint) stand side by side, one colour per LABEL (e.g. a planner setting).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def parse_spec(spec: str) -> tuple[str, str, Path]:
    try:
        key, path = spec.split("=", 1)
        group, label = key.split("/", 1)
    except ValueError:
        raise SystemExit(f"bad spec {spec!r}: expected GROUP/LABEL=path/to/eval.json") from None
    return group, label, Path(path)


def episode_returns(path: Path) -> np.ndarray:
    data = json.loads(path.read_text())
    return np.concatenate([np.asarray(r["returns"], float) for r in data["runs"]])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("specs", nargs="+", help="GROUP/LABEL=eval.json")
    ap.add_argument("--title", default="")
    ap.add_argument("--groups", help="comma-separated group order (default: first appearance)")
    ap.add_argument("--ylabel", default="eval return (episodes as dots)")
    args = ap.parse_args(argv)
    rows = [parse_spec(s) for s in args.specs]
    groups = args.groups.split(",") if args.groups else list(dict.fromkeys(g for g, _, _ in rows))
    labels = list(dict.fromkeys(lab for _, lab, _ in rows))
    width = 0.8 / len(labels)
    fig, ax = plt.subplots(figsize=(1.6 + 1.4 * len(groups) * max(1, len(labels) / 2), 3.6))
    for j, label in enumerate(labels):
        legend = label
        for i, group in enumerate(groups):
            paths = [p for g, lab, p in rows if g == group and lab == label]
            if not paths:
                continue
            r = episode_returns(paths[0])
            x = i + (j - (len(labels) - 1) / 2) * width
            ax.bar(x, r.mean(), width * 0.9, color=f"C{j}", label=legend)
            legend = None
            ax.plot(np.full(len(r), x), r, "k.", ms=3)
            ax.text(x, r.mean(), f"{r.mean():.0f}", ha="center", va="bottom", fontsize=7)
    ax.set_xticks(range(len(groups)), groups)
    ax.set_ylabel(args.ylabel)
    ax.set_title(args.title, fontsize=9)
    ax.legend(fontsize=7, loc="upper left")
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

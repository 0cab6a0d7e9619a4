"""Host-side run logging: progress bar, JSONL, TensorBoard, PNG plots.

Library choices: ``tqdm`` (progress, rate and ETA), ``tensorboardX`` (TensorBoard events without
TensorFlow), ``matplotlib`` (PNG plots, Agg backend), JSON Lines for a metrics file any tool reads.

Rows are ``{"step": env_steps, "seed": i, "kind": "train" | "eval", <metric>: value, ...}``, one per
seed per log point; plots show the mean over seeds with a min-max band.
"""

from __future__ import annotations

import json
import math
import time
from collections import defaultdict
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from tqdm import tqdm

PLOTS = {
    "returns.png": ("Return", ["eval/return", "eval/return_prior", "train/return"]),
    "world_model.png": (
        "World-model losses",
        ["wm/loss/obs", "wm/loss/reward", "wm/kl", "wm/loss/total", "wm/err/reward_mse"],
    ),
    "violations.png": ("Planner constraint violations", ["plan/dyn_viol", "plan/act_viol"]),
    "value.png": ("Value / actor losses", ["value/loss", "value/mean", "actor/loss"]),
}


def _finite(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


def read_rows(path: str | Path) -> tuple[list[dict], str | None]:
    """The rows of a ``metrics.jsonl`` and its cut-off last line, if any (what a kill mid-write
    leaves: rows are appended one line at a time, so only the last can be torn). A bad line
    anywhere else is damage, not a torn write: ValueError naming the file and line."""
    lines = Path(path).read_text().splitlines()
    rows = []
    for i, line in enumerate(lines):
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            if i == len(lines) - 1:
                return rows, line
            raise ValueError(
                f"{path}: line {i + 1} is not a JSON row (only the last line can be cut off by a "
                "crash); repair or remove it"
            ) from None
    return rows, None


class RunLog:
    """Writes ``metrics.jsonl``, ``tb/seed<i>/`` events and ``plots/*.png`` under ``run_dir``."""

    def __init__(
        self,
        run_dir: str | Path,
        total_steps: int,
        num_seeds: int,
        start_step: int = 0,
        progress: bool = True,
        enabled: bool = True,
    ):
        """``enabled=False`` (non-main processes of a multi-process run) writes nothing;
        ``progress=False`` prints one plain line per update instead of the bar (log files)."""
        self.enabled = enabled
        self.plain = enabled and not progress
        self.total, self._t0 = total_steps, time.perf_counter()
        # The plain ETA's rate is measured from the first progress call: the first chunk (the
        # random-action prefill) runs ~30x faster than training and made early ETAs ~25% short.
        self._rate_from: tuple[float, int] | None = None
        self.latest: dict[str, float] = {}
        self.bar = tqdm(
            total=total_steps,
            initial=start_step,
            unit="step",
            unit_scale=True,
            dynamic_ncols=True,
            disable=not (progress and enabled),
            smoothing=0.3,
        )
        if not enabled:
            return
        self.dir = Path(run_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        (self.dir / "plots").mkdir(exist_ok=True)
        self.path = self.dir / "metrics.jsonl"
        self.rows: list[dict] = []
        self.torn: str | None = None  # a cut-off last row dropped on resume (reported by the run)
        if self.path.exists():  # resume: keep history (drop rows past the resume point)
            self.rows, self.torn = read_rows(self.path)
            self.rows = [r for r in self.rows if r.get("step", 0) <= start_step]
            # rewritten whole, atomically: a crash here leaves the old file, never half of it
            tmp = self.path.with_suffix(".jsonl.tmp")
            tmp.write_text("".join(json.dumps(r) + "\n" for r in self.rows))
            tmp.replace(self.path)
        self.file = open(self.path, "a")
        self.num_seeds = num_seeds
        self.tb = None
        self._tb_dir = self.dir / "tb"

    def _writers(self):
        if self.tb is None:
            from tensorboardX import SummaryWriter

            self.tb = [SummaryWriter(str(self._tb_dir / f"seed{i}")) for i in range(self.num_seeds)]
        return self.tb

    def write(self, step: int, kind: str, per_seed: Mapping[str, np.ndarray]) -> None:
        """Log ``{metric: [num_seeds]}`` at env step ``step`` (NaN entries are skipped)."""
        if not self.enabled:
            return
        writers = self._writers()
        for i in range(self.num_seeds):
            row = {"step": int(step), "seed": i, "kind": kind}
            for key, values in per_seed.items():
                v = float(np.asarray(values)[i])
                if math.isfinite(v):
                    row[key] = v
                    writers[i].add_scalar(key, v, step)
            self.rows.append(row)
            self.file.write(json.dumps(row) + "\n")
        self.file.flush()
        for key, values in per_seed.items():
            v = np.asarray(values, np.float64)
            if np.isfinite(v).any():
                self.latest[key] = float(np.nanmean(v))

    def progress(self, step: int, extra: Mapping[str, str] | None = None) -> None:
        """Advance the bar to ``step`` and show the latest train/eval return."""
        post = {}
        for key, name in (("train/return", "train"), ("eval/return", "eval")):
            if key in self.latest:
                post[name] = f"{self.latest[key]:.1f}"
        post.update(extra or {})
        self.bar.set_postfix(post, refresh=False)
        self.bar.update(max(0, step - self.bar.n))
        if self.plain:
            now = time.perf_counter()
            elapsed = now - self._t0
            if self._rate_from is None:
                self._rate_from = (now, step)
            t_from, step_from = self._rate_from
            rate = (step - step_from) / max(now - t_from, 1e-9)
            eta = (self.total - step) / rate if rate > 0 else float("nan")
            fields = " ".join(f"{k} {v}" for k, v in post.items())
            print(
                f"step {step}/{self.total} {fields} elapsed {elapsed / 60:.1f}min "
                f"eta {f'{eta / 60:.1f}min' if math.isfinite(eta) else '-'}",
                flush=True,
            )

    def message(self, text: str) -> None:
        self.bar.write(text)

    def plot(self) -> list[Path]:
        """Redraw the PNG plots from all rows so far."""
        if not self.enabled:
            return []
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        series: dict[str, dict[int, dict[int, float]]] = defaultdict(lambda: defaultdict(dict))
        for row in self.rows:
            for key, v in row.items():
                if key in ("step", "seed", "kind") or not _finite(v):
                    continue
                series[key][row["step"]][row["seed"]] = v
        written = []
        for fname, (title, keys) in PLOTS.items():
            present = [k for k in keys if k in series]
            if not present:
                continue
            fig, axes = plt.subplots(
                1, len(present), figsize=(4.2 * len(present), 3.2), squeeze=False
            )
            for ax, key in zip(axes[0], present, strict=True):
                steps = np.array(sorted(series[key]))
                vals = [np.array(list(series[key][s].values())) for s in steps]
                mean = np.array([v.mean() for v in vals])
                lo = np.array([v.min() for v in vals])
                hi = np.array([v.max() for v in vals])
                ax.plot(steps, mean, marker="o" if len(steps) < 30 else None, ms=3)
                ax.fill_between(steps, lo, hi, alpha=0.25)
                ax.set_title(key)
                ax.set_xlabel("env steps")
                if key.startswith("plan/") and np.all(mean > 0):
                    ax.set_yscale("log")
                ax.grid(alpha=0.3)
            fig.suptitle(f"{title} (mean over {self.num_seeds} seed(s), band = min..max)")
            fig.tight_layout()
            path = self.dir / "plots" / fname
            fig.savefig(path, dpi=90)
            plt.close(fig)
            written.append(path)
        return written

    def close(self) -> None:
        self.bar.close()
        if not self.enabled:
            return
        self.file.close()
        if self.tb is not None:
            for w in self.tb:
                w.close()


def summarize_chunk(stacked: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Reduce a chunk's stacked metrics ``{key: [seeds, iterations, ...]}`` (NaN where the
    event did not happen) to ``{key: [seeds]}`` means over the events that did."""
    out = {}
    for key, v in stacked.items():
        v = np.asarray(v, np.float64)
        flat = v.reshape(v.shape[0], -1)
        with np.errstate(invalid="ignore"):
            count = np.isfinite(flat).sum(1)
            total = np.where(np.isfinite(flat), flat, 0.0).sum(1)
            out[key] = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return out

"""The plain progress lines (``--no-progress``, log files) give an ETA a user can plan by."""

from __future__ import annotations

import re

from mjx_collo import metrics


def test_eta_is_measured_after_the_prefill_chunk(tmp_path, monkeypatch, capsys):
    """The first chunk is random-action prefill, far faster than training: a rate that counted it
    promised the run ~25% early. Clock (s): prefill 5k steps in 12 s, then 5k steps per 300 s."""
    clock = iter([0.0, 12.0, 312.0, 612.0])
    monkeypatch.setattr(metrics.time, "perf_counter", lambda: next(clock))
    log = metrics.RunLog(tmp_path, total_steps=100_000, num_seeds=1, progress=False)
    for step in (5_000, 10_000, 15_000):
        log.progress(step)
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].endswith("eta -"), lines[0]
    etas = [float(re.search(r"eta ([\d.]+)min", line).group(1)) for line in lines[1:]]
    # 90k and 85k steps left at 1 step per 60 ms: 90.0 and 85.0 min (counting the prefill: 72.0)
    assert etas == [90.0, 85.0], lines
    elapsed = [float(re.search(r"elapsed ([\d.]+)min", line).group(1)) for line in lines]
    assert elapsed == [0.2, 5.2, 10.2], lines

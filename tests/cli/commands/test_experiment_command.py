"""``recslam experiment``: argument parsing, budgets and the timing estimates (the full runs are
exercised by tests/e2e and benchmarks/results/bandwidth.md)."""

from __future__ import annotations

import argparse
import json

import pytest

from common.errors import RecslamError
from recslam.commands import experiment


def test_bandwidth_subcommand_parses_budgets() -> None:
    parser = argparse.ArgumentParser()
    experiment.register(parser.add_subparsers())
    args = parser.parse_args(["experiment", "bandwidth", "--budgets", "unlimited,200,50"])
    assert args.func is experiment.run
    assert experiment.parse_budgets(args.budgets) == [None, 200.0, 50.0]
    with pytest.raises(RecslamError, match="'fast'"):
        experiment.parse_budgets("unlimited,fast")
    with pytest.raises(RecslamError, match="positive"):
        experiment.parse_budgets("0")


def test_timing_from_samples(tmp_path) -> None:
    # Robot "a" (10 frames): frames 0-4 decoded at t=100 (on time for frame 0), the rest at
    # t=102; camera time of frame i is 100 + i/20, so frame 9 is 102 - 100.45 = 1.55 s late.
    def sample(t: float, frames: int, keyframes: int) -> dict:
        return {"time": t, "edge": {"robots": {"a": {"frames_decoded": frames}}},
                "cloud": {"keyframes": keyframes}}  # fmt: skip

    samples = [sample(100.0, 5, 1), sample(102.0, 10, 2), sample(103.0, 10, 2)]
    path = tmp_path / "samples.jsonl"
    path.write_text("".join(json.dumps(s) + "\n" for s in samples))
    t = experiment.timing(path, {"a": 10})
    assert t["frame_delay_max_s"] == pytest.approx(2.0 - 5 / 20)
    late = [102.0 - (100.0 + i / 20) for i in range(5, 10)]
    assert t["frame_delay_mean_s"] == pytest.approx(
        sum(late) / 10 - sum(i / 20 for i in range(5)) / 10
    )
    assert t["kf_lag_s"] == pytest.approx(102.0 - (100.0 + 10 / 20))

"""``recslam experiment bandwidth``: its options become a :class:`lab.bandwidth.BandwidthConfig`
(the experiment itself is tested in tests/lab/test_bandwidth.py)."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from common.errors import RecslamError
from lab.bandwidth import BandwidthConfig
from recslam.commands import experiment


def parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    experiment.register(parser.add_subparsers())
    return parser.parse_args(["experiment", "bandwidth", *argv])


def test_bandwidth_defaults() -> None:
    from sim.netem import shaping_unavailable

    args = parse([])
    assert args.func is experiment.run
    assert experiment.bandwidth_config(args) == BandwidthConfig(
        data=Path("data/synth"),
        budgets=(None, 500.0, 200.0, 100.0, 50.0),
        robots=(),
        out=Path("out/bandwidth"),
        timeout_s=1800.0,
        shaper="tbf" if shaping_unavailable() is None else "proxy",  # --shaper auto
    )
    assert experiment.bandwidth_config(parse(["--shaper", "proxy"])).shaper == "proxy"


def test_bandwidth_options_reach_the_config() -> None:
    argv = ["--data", "d", "--budgets", "unlimited,200,50", "--robots", "robot0,robot2,"]
    config = experiment.bandwidth_config(parse([*argv, "--out", "o", "--timeout", "60"]))
    assert config.data == Path("d") and config.out == Path("o") and config.timeout_s == 60.0
    assert config.budgets == (None, 200.0, 50.0)
    assert config.robots == ("robot0", "robot2")
    with pytest.raises(RecslamError, match="'fast'"):
        experiment.bandwidth_config(parse(["--budgets", "unlimited,fast"]))


def test_a_missing_dataset_is_a_usage_error(tmp_path: Path, capsys) -> None:
    from recslam.cli import main

    code = main(["experiment", "bandwidth", "--data", str(tmp_path / "no"), "--out", str(tmp_path)])
    assert code == 2
    assert "no such dataset folder" in capsys.readouterr().err

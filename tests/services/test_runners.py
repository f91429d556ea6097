"""The services' entry points: ``recslam <tier>`` and ``python -m services.<tier>`` parse the
same options (defined once in ``services/<tier>/runner.py``) into the same run config, and
the modules run without the command-line package."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from common.links import WireFormat
from recslam.cli import build_parser
from services.cloud import __main__ as cloud_main
from services.cloud.runner import CloudRunConfig
from services.cloud.runner import config_from_args as cloud_config
from services.edge import __main__ as edge_main
from services.edge.runner import EdgeRunConfig
from services.edge.runner import config_from_args as edge_config
from services.robot import __main__ as robot_main
from services.robot.runner import config_from_args as robot_config

ROOT = Path(__file__).resolve().parents[2]
SECRET = "runner-test-secret-0123456789"


def _both(tier: str, argv: list[str]):
    """The arguments as ``recslam TIER ARGV`` and as ``python -m services.TIER ARGV``."""
    cli = build_parser().parse_args([tier, *argv])
    main = {"cloud": cloud_main, "edge": edge_main, "robot": robot_main}[tier]
    return cli, main.build_parser().parse_args(argv)


def test_cloud_options_build_one_config_both_ways(tmp_path) -> None:
    argv = ["--listen", "127.0.0.1:7101", "--no-mbp", "--dashboard-port", "0", "--wire", "raw"]
    argv += ["--output-every", "5"]
    argv += ["--state-dir", str(tmp_path), "--stats-out", str(tmp_path / "s.json")]
    argv += ["--record", str(tmp_path / "u.rec")]
    cli, main = _both("cloud", argv)
    config = cloud_config(cli)
    assert config == cloud_config(main)
    assert config.listen == ("127.0.0.1", 7101) and config.wire is WireFormat.RAW
    assert not config.mbp and config.full_ba and config.output_every_s == 5.0
    defaults, _ = _both("cloud", ["--state-dir", "s"])
    assert cloud_config(defaults) == CloudRunConfig(state_dir=Path("s"))


def test_edge_options_build_one_config_both_ways(tmp_path) -> None:
    argv = ["--listen", "127.0.0.1:7001", "--cloud", "cloud:7100", "--worker", "thread"]
    argv += ["--agent-id", "edge-2", "--wire", "raw", "--state-dir", str(tmp_path)]
    cli, main = _both("edge", [*argv, "--time-offset-ms", "-7.5"])
    config = edge_config(cli)
    assert config == edge_config(main)
    assert config.cloud == ("cloud", 7100) and config.worker == "thread"
    assert config.time_offset_ms == -7.5  # held fixed
    defaults, _ = _both("edge", [])
    assert edge_config(defaults) == EdgeRunConfig()
    assert EdgeRunConfig().time_offset_ms is None  # auto: estimated online
    auto, _ = _both("edge", ["--time-offset-ms", "auto"])
    assert edge_config(auto).time_offset_ms is None


def test_robot_options_build_one_config_both_ways(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("RECSLAM_SECRET", SECRET)
    argv = ["--dataset", str(tmp_path), "--edge", "edge:7000", "--agent-id", "r1"]
    argv += ["--rate", "max", "--max-frames", "9"]
    cli, main = _both("robot", argv)
    config = robot_config(cli)
    assert config == robot_config(main)
    assert config.max_frames == 9 and config.secret.operator == SECRET.encode()


def test_service_entry_points_do_not_load_the_cli_lab_or_sim() -> None:
    code = (
        "import sys\n"
        "import services.cloud.__main__, services.edge.__main__, services.robot.__main__\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('recslam', 'lab', 'sim')))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "[]"


@pytest.mark.parametrize(
    ("tier", "argv", "message"),
    [
        ("cloud", ["--state-dir", "{tmp}/state", "--dashboard-port", "0"], "no shared secret"),
        ("edge", [], "no shared secret"),
        ("edge", ["--time-offset-ms", "120"], "beyond ±50 ms"),
        ("robot", ["--dataset", "{tmp}/none", "--edge", "h:1", "--agent-id", "r"], "does not"),
    ],
)
def test_configuration_errors_exit_2(tmp_path, tier, argv, message) -> None:
    env = {k: v for k, v in os.environ.items() if k != "RECSLAM_SECRET"}
    if tier == "robot":
        env["RECSLAM_SECRET"] = SECRET
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    out = subprocess.run(
        [sys.executable, "-m", f"services.{tier}", *argv],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 2, out.stderr
    assert message in out.stderr


def test_cloud_module_runs_and_stops_on_sigterm(tmp_path) -> None:
    """``python -m services.cloud`` as a real process: it announces its address on stdout,
    writes its stats, and SIGTERM stops it with exit code 0."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    stats = tmp_path / "cloud.json"
    argv = ["--listen", f"127.0.0.1:{port}", "--state-dir", str(tmp_path / "state"), "-v"]
    argv += ["--dashboard-port", "0", "--output-every", "0", "--stats-out", str(stats)]
    env = {**os.environ, "RECSLAM_SECRET": SECRET}
    with (tmp_path / "cloud.log").open("w") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "services.cloud", *argv],
            cwd=ROOT,
            env=env,
            stdout=subprocess.PIPE,
            stderr=log,
            text=True,
        )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert line.startswith(f"cloud listening on 127.0.0.1:{port}"), (
            line + (tmp_path / "cloud.log").read_text()
        )
        proc.send_signal(signal.SIGTERM)
        rest, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, (tmp_path / "cloud.log").read_text()
    assert "cloud stopping" in rest
    assert stats.exists() and '"links"' in stats.read_text()
    assert "INFO" in (tmp_path / "cloud.log").read_text()  # -v: the shared logging set-up

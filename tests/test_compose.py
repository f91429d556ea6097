"""Static checks of docker-compose.yml (no Docker engine runs on the test machines)."""

from pathlib import Path

import yaml

from recslam.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]


def test_compose_commands_exist_in_cli() -> None:
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    parser = build_parser()
    assert compose["services"], "no services"
    for name, service in compose["services"].items():
        command = service["command"]
        assert command[0] == "recslam", name
        args = parser.parse_args(command[1:])  # raises SystemExit on an unknown command/flag
        assert callable(args.func), name
        for volume in service.get("volumes", []):
            source = volume.split(":", 1)[0]
            assert source in compose.get("volumes", {}) or source.startswith("."), volume

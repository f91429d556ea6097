"""The one CLI: every subcommand parses and prints help."""

import subprocess
import sys

import pytest

from recslam.cli import COMMAND_MODULES, build_parser, main


def subcommands() -> list[str]:
    parser = build_parser()
    action = next(a for a in parser._actions if a.dest == "command")
    return sorted(action.choices)


def test_every_command_module_registers_something() -> None:
    names = subcommands()
    assert len(names) >= len(COMMAND_MODULES)
    for expected in ("demo", "dataset", "robot", "edge", "cloud", "dashboard", "eval", "vocab"):
        assert expected in names


@pytest.mark.parametrize("name", subcommands())
def test_help_of_each_subcommand(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main([name, "--help"])
    assert exc.value.code == 0
    assert "usage: recslam" in capsys.readouterr().out


def test_console_entry_point_runs() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "recslam", "--help"], capture_output=True, text=True, check=True
    )
    assert "COMMAND" in out.stdout


def test_unknown_command_is_an_error(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["no-such-command"])
    assert exc.value.code == 2
    assert "invalid choice" in capsys.readouterr().err

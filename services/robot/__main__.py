"""``python -m services.robot ARGS``: the robot service, with the options of ``recslam robot``
(defined once in :mod:`services.robot.runner`) and its logging (``-v`` info, ``-vv`` debug)."""

from __future__ import annotations

import argparse
import sys

from common.entry import module_main, service_parser
from services.robot.runner import add_arguments, config_from_args, serve


def build_parser() -> argparse.ArgumentParser:
    return service_parser(
        "python -m services.robot",
        "A robot: play a sequence, track, code and send frames to an edge.",
        add_arguments,
    )


def main(argv: list[str] | None = None) -> int:
    def run(args: argparse.Namespace) -> int:
        return serve(config_from_args(args))

    return module_main(build_parser(), run, argv)


if __name__ == "__main__":
    sys.exit(main())

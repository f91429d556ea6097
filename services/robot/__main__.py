"""``python -m services.robot`` = ``recslam robot`` (same arguments, see commands/robot.py)."""

from __future__ import annotations

import argparse
import logging
import sys

from common.errors import RecslamError
from recslam.commands import robot


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m services.robot")
    sub = parser.add_subparsers(dest="command", required=True)
    robot.register(sub)
    sub.choices["robot"].add_argument(
        "-v", "--verbose", action="count", default=0, help="more logging"
    )
    args = parser.parse_args(["robot", *(sys.argv[1:] if argv is None else argv)])
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose, 2),
        format="%(asctime)s %(levelname)-7s %(name)s: %(message)s",
    )
    try:
        return int(args.func(args))
    except RecslamError as exc:
        print(f"robot: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

"""``recslam`` entry point: builds the argument parser from the command modules.

Each module in ``recslam.commands`` exposes ``register(subparsers)``, which adds its parser(s)
and sets ``func`` (``Namespace -> int`` exit code). Heavy imports happen inside ``func`` so
``--help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from common.errors import RecslamError
from common.logs import add_verbosity_argument, setup_logging

# Order is the order shown by ``recslam --help``.
COMMAND_MODULES = (
    "demo",
    "dataset",
    "robot",
    "edge",
    "cloud",
    "dashboard",
    "evaluate",
    "vocab",
    "keys",
    "experiment",
)

log = logging.getLogger(__name__)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="recslam",
        description="Robot-edge-cloud collaborative visual-inertial SLAM.",
    )
    add_verbosity_argument(parser)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(f"recslam.commands.{name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    setup_logging(args.verbose)
    try:
        return int(args.func(args) or 0)
    except RecslamError as exc:
        print(f"recslam {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130

"""``python -m services.edge ARGS``: the edge service, with the options of ``recslam edge``
(defined once in :mod:`services.edge.runner`) and its logging (``-v`` info, ``-vv`` debug)."""

from __future__ import annotations

import argparse
import functools
import sys

from common.errors import RecslamError
from common.logs import add_verbosity_argument, setup_logging
from services.edge.runner import add_arguments, config_from_args, serve


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m services.edge",
        description="The edge tier: per-robot VIO, feedback to robots, uplink to the cloud.",
    )
    add_verbosity_argument(parser)
    add_arguments(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    setup_logging(args.verbose)
    try:
        return serve(config_from_args(args), announce=functools.partial(print, flush=True))
    except RecslamError as exc:
        print(f"{parser.prog}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())

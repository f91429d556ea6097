"""``python -m services.cloud ARGS``: the cloud service, with the options of ``recslam cloud``
(defined once in :mod:`services.cloud.runner`) and its logging (``-v`` info, ``-vv`` debug)."""

from __future__ import annotations

import argparse
import functools
import sys

from common.errors import RecslamError
from common.logs import add_verbosity_argument, setup_logging
from services.cloud.runner import add_arguments, config_from_args, serve


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m services.cloud",
        description="The cloud tier: map fusion, global optimisation, MBP, dashboard.",
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

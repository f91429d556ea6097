"""Logging set-up of every entry point (``recslam`` and ``python -m services.<tier>``).

One format and one verbosity flag, so that a service logs the same whether it was started by
the command line or as a module: warnings by default, ``-v`` info, ``-vv`` debug, on stderr
(stdout carries the services' status lines, which supervisors read).
"""

from __future__ import annotations

import argparse
import logging
import sys

LOG_FORMAT = "%(asctime)s %(levelname)-7s %(name)s: %(message)s"


def add_verbosity_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``-v/--verbose`` (a count, ``args.verbose``) to ``parser``."""
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="more logging (-v info, -vv debug)"
    )


def setup_logging(verbosity: int) -> None:
    """Configure the root logger: WARNING, INFO (1) or DEBUG (2 or more) on stderr."""
    level = logging.WARNING - 10 * min(max(verbosity, 0), 2)
    logging.basicConfig(level=level, format=LOG_FORMAT, stream=sys.stderr)

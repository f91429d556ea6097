"""``python -m services.cloud ARGS``: the cloud service, with the options of ``recslam cloud``
(defined once in :mod:`services.cloud.runner`) and its logging (``-v`` info, ``-vv`` debug)."""

from __future__ import annotations

import argparse
import functools
import sys

from common.entry import module_main, service_parser
from services.cloud.runner import add_arguments, config_from_args, serve


def build_parser() -> argparse.ArgumentParser:
    return service_parser(
        "python -m services.cloud",
        "The cloud tier: map fusion, global optimisation, MBP, dashboard.",
        add_arguments,
    )


def main(argv: list[str] | None = None) -> int:
    def run(args: argparse.Namespace) -> int:
        return serve(config_from_args(args), announce=functools.partial(print, flush=True))

    return module_main(build_parser(), run, argv)


if __name__ == "__main__":
    sys.exit(main())

"""``python -m services.edge ARGS``: the ``recslam edge`` command without the CLI wrapper."""

import argparse
import logging
import sys

from recslam.commands import edge


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m services.edge")
    sub = parser.add_subparsers(dest="command", required=True)
    edge.register(sub)
    args = parser.parse_args(["edge", *(sys.argv[1:] if argv is None else argv)])
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s: %(message)s"
    )
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())

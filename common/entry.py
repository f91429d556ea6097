"""What every ``python -m services.<tier>`` entry point shares: its ``main``, the type of the
status-line callback the runners take, and the parsing of a listen address.

A tier's ``__main__`` is its parser (the options come from the tier's runner, defined once for
it and for ``recslam <tier>``) and one call of :func:`module_main`: logging as the ``recslam``
command sets it up (:mod:`common.logs`), a :class:`~common.errors.RecslamError` as
``PROG: error: ...`` with exit code 2, Ctrl-C as exit code 130.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import signal
from collections.abc import Awaitable, Callable, Sequence
from pathlib import Path

from common.errors import RecslamError
from common.logs import add_verbosity_argument, setup_logging
from common.protocol.credentials import SECRET_ENV, parse_address
from common.transport.tls import TlsFiles

Announce = Callable[[str], None]
"""Where a service's status lines go (the entry points print them on stdout, where
supervisors and the demo orchestration read them)."""


def listen_address(text: str) -> tuple[str, int]:
    """``HOST:PORT`` or ``PORT`` (all interfaces) of a service's ``--listen``."""
    return parse_address(text, default_host="0.0.0.0")


def add_security_arguments(p: argparse.ArgumentParser) -> None:
    """``--key-file``, ``--secret-file`` and ``--tls-cert/--tls-key/--tls-ca``: the same on
    every service (see ``common.protocol.credentials`` and ``common.transport.tls``). The
    files default to ``$RECSLAM_KEY_FILE``, ``$RECSLAM_TLS_CERT``, ``$RECSLAM_TLS_KEY`` and
    ``$RECSLAM_TLS_CA`` (compose sets them: ``docker-compose.secure.yml``)."""

    def env(name: str) -> Path | None:
        value = os.environ.get(name)
        return Path(value) if value else None

    p.add_argument(
        "--key-file",
        type=Path,
        default=env("RECSLAM_KEY_FILE"),
        metavar="F",
        help="this component's key file from `recslam keys new` (its own credential and what "
        "it may verify); default: the operator secret of --secret-file",
    )
    p.add_argument(
        "--secret-file",
        type=Path,
        default=None,
        metavar="F",
        help=f"operator secret file, derives every credential (default: ${SECRET_ENV})",
    )
    p.add_argument(
        "--tls-cert",
        type=Path,
        default=env("RECSLAM_TLS_CERT"),
        metavar="PEM",
        help="TLS certificate: listen with TLS (with --tls-key)",
    )
    p.add_argument(
        "--tls-key", type=Path, default=env("RECSLAM_TLS_KEY"), metavar="PEM", help="its key"
    )
    p.add_argument(
        "--tls-ca",
        type=Path,
        default=env("RECSLAM_TLS_CA"),
        metavar="PEM",
        help="CA bundle: connect with TLS and verify the server (frames are sealed either way; "
        "TLS is optional)",
    )


def add_give_up_argument(p: argparse.ArgumentParser, upstream: str) -> None:
    """``--give-up-after S`` (default ``$RECSLAM_GIVE_UP_AFTER``, else 0 = never): how long a
    service keeps trying to get a session with its ``upstream`` peer before it exits."""
    default = os.environ.get("RECSLAM_GIVE_UP_AFTER") or "0"
    p.add_argument(
        "--give-up-after",
        type=_seconds,
        default=default,  # a string: argparse converts it (and reports a bad one) as typed
        metavar="S",
        help=f"exit (code 4, one line saying why) after S seconds without a session with the "
        f"{upstream}: unreachable, timing out or closing before the handshake (default "
        "$RECSLAM_GIVE_UP_AFTER, else 0 = keep trying); a refused key exits at once (code 3)",
    )


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"{text!r}: seconds must be >= 0 (0 = never)")
    return value


def tls_from_args(args: argparse.Namespace) -> TlsFiles:
    return TlsFiles(args.tls_cert, args.tls_key, args.tls_ca)


def service_parser(
    prog: str, description: str, add_arguments: Callable[[argparse.ArgumentParser], None]
) -> argparse.ArgumentParser:
    """The parser of a tier's ``__main__``: ``-v`` and the tier's own options."""
    parser = argparse.ArgumentParser(prog=prog, description=description)
    add_verbosity_argument(parser)
    add_arguments(parser)
    return parser


def module_main(
    parser: argparse.ArgumentParser,
    run: Callable[[argparse.Namespace], int],
    argv: Sequence[str] | None = None,
) -> int:
    """Parse ``argv`` (default: the process's), set up logging and ``run`` the parsed
    arguments; returns its exit code (a RecslamError or Ctrl-C exits through the parser, with
    2 or 130)."""
    args = parser.parse_args(argv)
    setup_logging(args.verbose)
    try:
        return run(args)
    except RecslamError as exc:
        parser.exit(2, f"{parser.prog}: error: {exc}\n")  # argparse's own error exit
    except KeyboardInterrupt:
        parser.exit(130, "interrupted\n")


def stop_on_signals() -> asyncio.Event:
    """An event SIGINT and SIGTERM set, installed on the running loop.

    Call it before the service announces its address (a supervisor that signals right after
    the announcement must find the handlers in place) and after the service's modules are
    imported: importing pycolmap installs glog's failure handler for SIGTERM, which replaces
    an earlier one and aborts the process."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    return stop


async def run_until_signal(
    stop: asyncio.Event,
    tick: Callable[[], Awaitable[None]] | None = None,
    period_s: float = 1.0,
) -> None:
    """Return once ``stop`` (from :func:`stop_on_signals`) is set; meanwhile await ``tick``
    every ``period_s`` (a service's stats file, for instance)."""
    while not stop.is_set():
        if tick is not None:
            await tick()
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), period_s)

"""``recslam keys``: make and list the per-component key files (one identity per peer).

    recslam keys new --dir keys --edge edge --robot robot0 --robot robot1 --robot robot2
    recslam keys list --dir keys
    recslam keys tls --dir tls --name cloud --name edge --name 127.0.0.1

``new`` makes the operator secret ``DIR/operator.key`` if it is missing (keep it with the
operator; it derives every credential) and writes ``cloud.keys``, ``edge-<id>.keys`` and
``robot-<id>.keys``. Run it again with more ``--robot`` names to add robots: the files of
existing names come out the same. Give each component only its own file (``--key-file``):
a robot's file lets its holder be that robot and nothing else; an edge's lets it be that edge
and verify robots; the cloud's lets it verify edges.

``tls`` writes a self-signed certificate (its own CA) and key for the given host names, for
test sites and compose: servers take ``--tls-cert cert.pem --tls-key key.pem``, clients
``--tls-ca cert.pem``. Frames are sealed with the key files whether or not TLS is on.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "keys", help="make and list key files (one identity per peer)", description=__doc__
    )
    sub = p.add_subparsers(dest="keys_command", metavar="ACTION", required=True)
    new = sub.add_parser("new", help="issue the key files of a team (idempotent)")
    new.add_argument("--dir", type=Path, required=True, help="key directory (made if missing)")
    new.add_argument(
        "--edge", action="append", default=[], metavar="ID", help="an edge's agent id (repeat)"
    )
    new.add_argument(
        "--robot", action="append", default=[], metavar="ID", help="a robot's agent id (repeat)"
    )
    new.set_defaults(func=_new)
    show = sub.add_parser("list", help="who each key file in DIR is, with key fingerprints")
    show.add_argument("--dir", type=Path, required=True, help="key directory")
    show.set_defaults(func=_list)
    tls = sub.add_parser("tls", help="a self-signed TLS certificate for test sites and compose")
    tls.add_argument("--dir", type=Path, required=True, help="where cert.pem and key.pem go")
    tls.add_argument(
        "--name", action="append", required=True, metavar="HOST", help="a host name or IP (repeat)"
    )
    tls.set_defaults(func=_tls)


def _new(args: argparse.Namespace) -> int:
    from common.protocol.credentials import describe_keys, issue_keys

    for path in issue_keys(args.dir, args.edge, args.robot):
        print(describe_keys(path))
    return 0


def _list(args: argparse.Namespace) -> int:
    from common.protocol.credentials import CredentialsError, describe_keys

    files = sorted(args.dir.glob("*.keys"))
    if not files:
        raise CredentialsError(f"{args.dir}: no *.keys files (make them with `recslam keys new`)")
    for path in files:
        print(describe_keys(path))
    return 0


def _tls(args: argparse.Namespace) -> int:
    from common.transport.tls import make_self_signed

    cert, key = make_self_signed(args.dir, args.name)
    print(f"{cert} and {key} for {', '.join(args.name)}")
    return 0

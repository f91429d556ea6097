"""Where services get their peer address and shared secret: one rule for every tier.

``load_secret``: ``--secret-file`` contents (trailing newline stripped), else the
``RECSLAM_SECRET`` environment variable, else ``dev_default`` when the caller allows one (the
robot, with a logged warning), else an error. Secrets shorter than
:data:`common.protocol.auth.MIN_SECRET_SIZE` bytes are refused, and so is
:data:`PLACEHOLDER_SECRET`, the example value of ``docker/secret.env.example``.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from pathlib import Path

from common.errors import RecslamError
from common.protocol.auth import MIN_SECRET_SIZE

logger = logging.getLogger(__name__)

SECRET_ENV = "RECSLAM_SECRET"
PLACEHOLDER_SECRET = b"change-me-to-a-long-random-string"
"""The example value in ``docker/secret.env.example``: never a real secret."""


class CredentialsError(RecslamError, ValueError):
    """A malformed address or a missing/short shared secret (a ValueError for argparse)."""


def parse_address(text: str, default_host: str | None = None) -> tuple[str, int]:
    """``HOST:PORT`` (``[v6]:PORT`` for IPv6) -> (host, port).

    An empty host (``:7000``) means ``default_host`` when given (e.g. ``"0.0.0.0"`` for a
    listening address), else it is an error.
    """
    host, sep, port = text.rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not host and default_host is not None:
        host = default_host
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise CredentialsError(f"address {text!r} is not HOST:PORT (port 1..65535)")
    return host, int(port)


def load_secret(
    secret_file: str | Path | None,
    environ: Mapping[str, str] = os.environ,
    dev_default: bytes | None = None,
) -> bytes:
    """The shared secret (see the module docstring); CredentialsError names the source."""
    if secret_file is not None:
        path = Path(secret_file)
        try:
            secret = path.read_bytes().rstrip(b"\r\n")
        except OSError as exc:
            raise CredentialsError(f"{path}: cannot read the secret file ({exc})") from None
        source = str(path)
    elif environ.get(SECRET_ENV) is not None:
        secret = environ[SECRET_ENV].encode()
        source = f"${SECRET_ENV}"
    elif dev_default is not None:
        logger.warning(
            "no --secret-file and no $%s: using the development secret (never in deployment)",
            SECRET_ENV,
        )
        return dev_default
    else:
        raise CredentialsError(f"no shared secret: pass --secret-file or set ${SECRET_ENV}")
    if len(secret) < MIN_SECRET_SIZE:
        raise CredentialsError(
            f"{source}: secret is {len(secret)} bytes, need at least {MIN_SECRET_SIZE} bytes"
        )
    if secret == PLACEHOLDER_SECRET:
        raise CredentialsError(
            f"{source}: this is the placeholder secret of docker/secret.env.example; make a "
            "real one with 'make docker/secret.env' (or: python3 -c \"import secrets; "
            "print('RECSLAM_SECRET=' + secrets.token_hex(24))\" > docker/secret.env)"
        )
    return secret

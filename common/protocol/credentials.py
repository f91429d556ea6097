"""Where services get their peer address and their keys: one rule for every tier.

``load_keys``: a ``--key-file`` (what ``recslam keys new`` wrote for this component: see
below), else the operator secret from :func:`load_secret`, which derives every credential
(single-host runs and the demo).

``load_secret``: ``--secret-file`` contents (trailing newline stripped), else the
``RECSLAM_SECRET`` environment variable, else ``dev_default`` when the caller allows one (the
robot, with a logged warning), else an error. Secrets shorter than
:data:`common.protocol.auth.MIN_SECRET_SIZE` bytes are refused, and so is
:data:`PLACEHOLDER_SECRET`, the example value of ``docker/secret.env.example``.

Key files (JSON, ``"format": "recslam-keys/1"``, mode 0600), one per component, issued from
the operator secret (``operator.key``, which stays with the operator) by
:func:`issue_keys`:

- ``cloud.keys``: the edges' role key (the cloud verifies any edge, serves none else);
- ``edge-<id>.keys``: that edge's own credential (towards the cloud) and the robots' role key;
- ``robot-<id>.keys``: that robot's credential only: it can be that robot and nothing else.
"""

from __future__ import annotations

import json
import logging
import os
import secrets
from collections.abc import Mapping, Sequence
from pathlib import Path

from common.errors import RecslamError
from common.protocol import auth
from common.protocol.auth import MIN_SECRET_SIZE, Identity, Keyring

logger = logging.getLogger(__name__)

SECRET_ENV = "RECSLAM_SECRET"
PLACEHOLDER_SECRET = b"change-me-to-a-long-random-string"
"""The example value in ``docker/secret.env.example``: never a real secret."""
KEY_FORMAT = "recslam-keys/1"
OPERATOR_FILE = "operator.key"


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


def load_keys(
    key_file: str | Path | None,
    secret_file: str | Path | None = None,
    environ: Mapping[str, str] = os.environ,
    dev_default: bytes | None = None,
    identity: tuple[str, str] | None = None,
) -> Keyring:
    """This component's keys (see the module docstring). ``identity`` (role, agent id): a
    client's own; CredentialsError if the keys cannot prove it (e.g. another robot's file)."""
    if key_file is not None:
        if secret_file is not None:
            raise CredentialsError("give --key-file or --secret-file, not both")
        keyring = read_key_file(key_file)
        if identity is not None and keyring.credential(*identity) is None:
            own = keyring.own
            held = f"{own.role} {own.agent_id!r}" if own else "no identity of its own"
            raise CredentialsError(
                f"{key_file}: holds {held}, not {identity[0]} {identity[1]!r} "
                "(pass the key file issued for this agent id)"
            )
        return keyring
    return Keyring.from_secret(load_secret(secret_file, environ, dev_default))


def read_key_file(path: str | Path) -> Keyring:
    """Read a key file written by :func:`issue_keys`; CredentialsError names what is wrong."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        raise CredentialsError(f"{path}: cannot read the key file ({exc})") from None
    except ValueError as exc:
        raise CredentialsError(f"{path}: not a key file (invalid JSON: {exc})") from None
    if not isinstance(data, dict) or data.get("format") != KEY_FORMAT:
        raise CredentialsError(f"{path}: not a key file (format is not {KEY_FORMAT!r})")
    if path.stat().st_mode & 0o077:
        logger.warning("%s: readable by other users; chmod 600 it", path)
    try:
        own = data.get("identity")
        identity = (
            Identity(str(own["role"]), str(own["agent_id"]), bytes.fromhex(own["credential"]))
            if own
            else None
        )
        role_keys = tuple(
            (str(role), bytes.fromhex(key)) for role, key in dict(data.get("role_keys", {})).items()
        )
        operator = bytes.fromhex(data["operator"]) if data.get("operator") else None
        return Keyring(operator=operator, role_keys=role_keys, own=identity)
    except (KeyError, TypeError, ValueError, RecslamError) as exc:
        raise CredentialsError(f"{path}: malformed key file ({exc})") from None


def write_key_file(path: Path, keyring: Keyring, comment: str) -> None:
    """Write ``keyring`` to ``path`` (mode 0600, replaced atomically)."""
    data: dict[str, object] = {"format": KEY_FORMAT, "comment": comment}
    if keyring.own is not None:
        own = keyring.own
        data["identity"] = {
            "role": own.role,
            "agent_id": own.agent_id,
            "credential": own.credential.hex(),
        }
    if keyring.role_keys:
        data["role_keys"] = {role: key.hex() for role, key in keyring.role_keys}
    if keyring.operator is not None:
        data["operator"] = keyring.operator.hex()
    write_private(path, json.dumps(data, indent=1) + "\n")


def write_private(path: Path, text: str | bytes) -> None:
    """Write a secret file: mode 0600 from its creation, replaced atomically."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(text.encode() if isinstance(text, str) else text)
    tmp.replace(path)


def operator_secret(directory: Path) -> bytes:
    """The operator secret in ``directory`` (made, 32 random bytes, mode 0600, if absent)."""
    path = directory / OPERATOR_FILE
    if not path.exists():
        directory.mkdir(parents=True, exist_ok=True)
        write_private(path, secrets.token_hex(32) + "\n")
        logger.info("new operator secret %s", path)
    return load_secret(path)


def issue_keys(directory: Path, edges: Sequence[str], robots: Sequence[str]) -> list[Path]:
    """Write ``cloud.keys``, ``edge-<id>.keys`` and ``robot-<id>.keys`` into ``directory``
    from its operator secret (made if absent). Idempotent: the same secret and names give the
    same files, so it can be run again to add robots. Returns the files written."""
    operator = operator_secret(directory)
    robot_key, edge_key = auth.role_key(operator, "robot"), auth.role_key(operator, "edge")
    out = [directory / "cloud.keys"]
    write_key_file(out[0], Keyring(role_keys=(("edge", edge_key),)), "the cloud: verifies edges")
    for name in edges:
        own = Identity("edge", name, auth.agent_credential(edge_key, name))
        path = directory / f"edge-{name}.keys"
        keyring = Keyring(role_keys=(("robot", robot_key),), own=own)
        write_key_file(path, keyring, f"edge {name}: its credential, verifies robots")
        out.append(path)
    for name in robots:
        own = Identity("robot", name, auth.agent_credential(robot_key, name))
        path = directory / f"robot-{name}.keys"
        write_key_file(path, Keyring(own=own), f"robot {name}: its credential only")
        out.append(path)
    return out


def describe_keys(path: Path) -> str:
    """One line about a key file: who it is and what it can verify, with fingerprints."""
    keyring = read_key_file(path)
    parts = []
    if keyring.own is not None:
        own = keyring.own
        parts.append(f"is {own.role} {own.agent_id!r} ({auth.fingerprint(own.credential)})")
    for role, key in keyring.role_keys:
        parts.append(f"verifies any {role} ({auth.fingerprint(key)})")
    if keyring.operator is not None:
        parts.append(f"operator secret ({auth.fingerprint(keyring.operator)})")
    return f"{path.name}: " + "; ".join(parts)

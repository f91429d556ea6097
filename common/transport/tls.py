"""Optional TLS around the protocol (``--tls-cert/--tls-key/--tls-ca`` on every service).

Every frame is sealed by the protocol itself (``common.protocol.sealing``), so TLS is not
needed for integrity or secrecy between peers that hold their keys; it is there for sites
whose policy asks for TLS, or to pin servers by certificate. A server with a certificate
listens with TLS (and, given a CA, requires client certificates signed by it); a client with
a CA connects with TLS and verifies the server against it (host name included).
"""

from __future__ import annotations

import ssl
from dataclasses import dataclass
from pathlib import Path

from common.errors import RecslamError


class TlsError(RecslamError, ValueError):
    """A TLS option that cannot work: a missing half of a pair, an unreadable file."""


@dataclass(frozen=True)
class TlsFiles:
    """PEM files of one service.

    Attributes:
        cert, key: this service's certificate chain and private key (servers: needed to
            listen with TLS; clients: presented when the server asks for one).
        ca: the CA bundle that peers' certificates are checked against (clients: connect
            with TLS; servers: require client certificates).
    """

    cert: Path | None = None
    key: Path | None = None
    ca: Path | None = None

    def __post_init__(self) -> None:
        if (self.cert is None) != (self.key is None):
            raise TlsError("--tls-cert and --tls-key go together")
        for name in ("cert", "key", "ca"):
            path = getattr(self, name)
            if path is not None and not Path(path).is_file():
                raise TlsError(f"--tls-{name} {path}: no such file")

    @property
    def enabled(self) -> bool:
        return self.cert is not None or self.ca is not None

    def server_context(self) -> ssl.SSLContext | None:
        """The listening side's context, or None (plain TCP) without a certificate."""
        if self.cert is None:
            return None
        ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        ctx.minimum_version = ssl.TLSVersion.TLSv1_2
        self._load_chain(ctx)
        if self.ca is not None:
            self._load_ca(ctx)
            ctx.verify_mode = ssl.CERT_REQUIRED
        return ctx

    def client_context(self) -> ssl.SSLContext | None:
        """The connecting side's context, or None (plain TCP) without a CA."""
        if self.ca is None:
            return None
        ctx = ssl.create_default_context(ssl.Purpose.SERVER_AUTH)
        ctx.minimum_version = ssl.TLSVersion.TLSv1_2
        self._load_ca(ctx)
        if self.cert is not None:
            self._load_chain(ctx)
        return ctx

    def _load_chain(self, ctx: ssl.SSLContext) -> None:
        try:
            ctx.load_cert_chain(str(self.cert), str(self.key))
        except (OSError, ssl.SSLError) as exc:
            raise TlsError(f"--tls-cert {self.cert} / --tls-key {self.key}: {exc}") from None

    def _load_ca(self, ctx: ssl.SSLContext) -> None:
        try:
            ctx.load_verify_locations(cafile=str(self.ca))
        except (OSError, ssl.SSLError) as exc:
            raise TlsError(f"--tls-ca {self.ca}: {exc}") from None

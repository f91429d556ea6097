"""Optional TLS around the protocol (``--tls-cert/--tls-key/--tls-ca`` on every service).

Every frame is sealed by the protocol itself (``common.protocol.sealing``), so TLS is not
needed for integrity or secrecy between peers that hold their keys; it is there for sites
whose policy asks for TLS, or to pin servers by certificate. A server with a certificate
listens with TLS; a client with a CA connects with TLS and verifies the server against it
(host name included). Clients prove who they are with their credential, not a certificate,
so one service may hold a certificate for its listening side and a CA for its own links (an
edge: robots connect to it, it connects to the cloud).
"""

from __future__ import annotations

import ssl
from dataclasses import dataclass
from pathlib import Path

from common.errors import RecslamError
from common.protocol.credentials import write_private


class TlsError(RecslamError, ValueError):
    """A TLS option that cannot work: a missing half of a pair, an unreadable file."""


@dataclass(frozen=True)
class TlsFiles:
    """PEM files of one service.

    Attributes:
        cert, key: this service's certificate chain and private key: it listens with TLS.
        ca: the CA bundle servers' certificates are checked against: it connects with TLS.
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
        return ctx

    def client_context(self) -> ssl.SSLContext | None:
        """The connecting side's context, or None (plain TCP) without a CA."""
        if self.ca is None:
            return None
        ctx = ssl.create_default_context(ssl.Purpose.SERVER_AUTH)
        ctx.minimum_version = ssl.TLSVersion.TLSv1_2
        self._load_ca(ctx)
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


def make_self_signed(directory: Path, names: list[str], days: int = 365) -> tuple[Path, Path]:
    """Write ``cert.pem`` (self-signed, its own CA) and ``key.pem`` (mode 0600) for ``names``
    (DNS names or IP addresses) into ``directory``; for test sites and compose. Returns
    (cert, key)."""
    import datetime
    import ipaddress

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    if not names:
        raise TlsError("a certificate needs at least one name")
    alt: list[x509.GeneralName] = []
    for name in names:
        try:
            alt.append(x509.IPAddress(ipaddress.ip_address(name)))
        except ValueError:
            alt.append(x509.DNSName(name))
    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, names[0])])
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=days))
        .add_extension(x509.SubjectAlternativeName(alt), critical=False)
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .sign(key, hashes.SHA256())
    )
    directory.mkdir(parents=True, exist_ok=True)
    cert_path, key_path = directory / "cert.pem", directory / "key.pem"
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    pem = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    write_private(key_path, pem)
    return cert_path, key_path

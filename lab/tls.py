"""A throw-away TLS pair for tests and benchmarks of the links: the self-signed certificate
for ``localhost`` that ``recslam keys tls`` makes (:func:`common.transport.tls.make_self_signed`),
as ready contexts."""

from __future__ import annotations

import ssl
from pathlib import Path

from common.transport.tls import TlsFiles, make_self_signed


def self_signed_contexts(directory: Path) -> tuple[ssl.SSLContext, ssl.SSLContext]:
    """(server context, client context trusting it); key and certificate written into
    ``directory``."""
    cert, key = make_self_signed(directory, ["localhost"])
    server, client = TlsFiles(cert, key).server_context(), TlsFiles(ca=cert).client_context()
    assert server is not None and client is not None
    return server, client

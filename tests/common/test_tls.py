"""TLS as an option around the sealed protocol (``--tls-cert/--tls-key/--tls-ca``), over real
sockets, with per-identity key files as the services load them."""

from __future__ import annotations

import asyncio

import pytest

from common.entry import add_security_arguments, tls_from_args
from common.protocol import Blob, SessionConfig
from common.protocol.credentials import CredentialsError, issue_keys, load_keys
from common.transport import Client, Delivery, Server, TransportConfig, run
from common.transport.tls import TlsError, TlsFiles, make_self_signed

FAST = TransportConfig(reconnect_initial_delay=0.01, reconnect_max_delay=0.05)


@pytest.fixture
def pem(tmp_path):
    """``recslam keys tls``'s certificate for localhost and 127.0.0.1."""
    return make_self_signed(tmp_path, ["localhost", "127.0.0.1"])


def test_key_files_and_tls_files_carry_a_robot_to_its_edge(tmp_path, pem):
    cert, key = pem
    keys = tmp_path / "keys"
    issue_keys(keys, ["edge"], ["robot0"])
    edge_keys = load_keys(keys / "edge-edge.keys")
    robot_keys = load_keys(keys / "robot-robot0.keys", identity=("robot", "robot0"))
    got: list[bytes] = []

    async def on_message(d: Delivery) -> None:
        assert d.peer == "robot0" and d.role == "robot"
        got.append(d.message.data)

    async def main() -> None:
        server = Server(
            SessionConfig("edge", "edge", keys=edge_keys),
            on_message,
            ssl=TlsFiles(cert, key).server_context(),
        )
        host, port = await server.start()
        client = Client(
            SessionConfig("robot", "robot0", keys=robot_keys),
            on_message,
            "127.0.0.1",  # the certificate's IP address name is checked too
            port,
            ssl=TlsFiles(ca=cert).client_context(),
            server_hostname="127.0.0.1",
            transport=FAST,
        )
        plain = Client(
            SessionConfig("robot", "robot0", keys=robot_keys),
            on_message,
            host,
            port,
            transport=FAST,
        )
        await client.start()
        await plain.start()
        try:
            await client.send(Blob(1, b"over tls"))
            await client.flush()
            await asyncio.sleep(0.3)
            assert got == [b"over tls"]
            assert not plain.peer.connected  # a client without TLS never gets in
        finally:
            await plain.close()
            await client.close()
            await server.close()

    run(main())


def test_tls_options_fail_with_their_names(tmp_path, pem):
    cert, _ = pem
    with pytest.raises(TlsError, match="go together"):
        TlsFiles(cert=cert)
    with pytest.raises(TlsError, match="no such file"):
        TlsFiles(ca=tmp_path / "missing.pem")
    junk = tmp_path / "junk.pem"
    junk.write_text("not a certificate")
    with pytest.raises(TlsError, match=r"junk\.pem"):
        TlsFiles(ca=junk).client_context()
    assert TlsFiles().server_context() is None and TlsFiles().client_context() is None


def test_security_arguments_parse_for_every_service(pem):
    import argparse

    cert, key = pem
    p = argparse.ArgumentParser()
    add_security_arguments(p)
    args = p.parse_args(["--tls-cert", str(cert), "--tls-key", str(key), "--tls-ca", str(cert)])
    assert tls_from_args(args) == TlsFiles(cert, key, cert)
    with pytest.raises(SystemExit):
        p.parse_args(["--tls-cert"])


def test_key_file_errors_name_the_file(tmp_path):
    keys = tmp_path / "keys"
    issue_keys(keys, [], ["robot0"])
    with pytest.raises(CredentialsError, match=r"robot-robot0\.keys: holds robot 'robot0'"):
        load_keys(keys / "robot-robot0.keys", identity=("robot", "robot1"))
    bad = tmp_path / "bad.keys"
    bad.write_text("{}")
    with pytest.raises(CredentialsError, match=r"bad\.keys: not a key file"):
        load_keys(bad)
    with pytest.raises(CredentialsError, match="not both"):
        load_keys(keys / "robot-robot0.keys", tmp_path / "secret")
    # issued again: the same files (so robots can be added later)
    before = (keys / "robot-robot0.keys").read_bytes()
    issue_keys(keys, ["edge"], ["robot0", "robot1"])
    assert (keys / "robot-robot0.keys").read_bytes() == before
    assert (keys / "robot-robot0.keys").stat().st_mode & 0o077 == 0

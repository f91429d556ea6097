"""asyncio transport for ``common.protocol``: TCP (optionally TLS) clients and servers.

The sans-I/O :class:`~common.protocol.session.Session` does the protocol; this module only
moves bytes, arms one timer per connection (``loop.call_at`` on ``Session.get_timer()``)
and runs the application's handler.

A service uses it like this::

    async def on_message(d: Delivery) -> None:      # runs once per message, in order
        ...                                          # when it returns, the message is acked

    server = Server(SessionConfig("edge", "edge-0", secret), on_message)
    host, port = await server.start("0.0.0.0", 7000)
    await server.send("robot-1", Blob(0, b"..."))    # waits while that outbox is full

    client = Client(SessionConfig("robot", "robot-1", secret), on_message, host, port)
    await client.start()                             # connects, reconnects with backoff
    seq = await client.send(Blob(0, b"..."))         # queued even while disconnected
    await client.flush()                             # until the peer's handler took all
    client.counters()                                # plain-data traffic counters

Delivery is exactly-once and in order per link across reconnects. Across a restart of the
receiving process it is exactly-once when a :class:`~common.protocol.store.DeliveryStore`
gives back the saved position (see ``common/protocol/store.py``). A handler that raises
does not ack: the connection is dropped and the message is redelivered after reconnect.
A handler that replies to the same peer should use ``send_nowait`` (or a separate task)
rather than await a full outbox: two handlers each waiting for the other to deliver would
wait forever. Agent ids must be unique: a second connection with the same id replaces the
first.
"""

import common.links  # noqa: F401  (registers every link's message types for decoding)
from common.transport.connection import Delivery, Peer, TransportConfig, run
from common.transport.endpoints import Client, Server, link_load

__all__ = ["Client", "Delivery", "Peer", "Server", "TransportConfig", "link_load", "run"]

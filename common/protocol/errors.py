"""Protocol errors, split by blame (as in h11).

- :class:`LocalProtocolError`: this process misused the protocol (sent an oversized frame,
  a message with a field of the wrong type, used a closed session). A bug or a config error
  here; the peer did nothing wrong.
- :class:`RemoteProtocolError`: the peer sent something illegal (bad magic, bad CRC, unknown
  message type, wrong field types, a frame out of state, a failed authentication). The
  connection to that one peer must be closed; the service keeps running.
- :class:`PeerTimeoutError`: the peer went silent for longer than the idle timeout (dead peer) or
  did not finish the handshake in time.
"""

from common.errors import RecslamError


class ProtocolError(RecslamError):
    """Base of every error raised by ``common.protocol``."""


class LocalProtocolError(ProtocolError):
    """This side broke the protocol (caller bug or configuration error)."""


class OutboxFullError(LocalProtocolError):
    """The bounded outbox has no room; wait for acknowledgements and try again."""


class RemoteProtocolError(ProtocolError):
    """The peer broke the protocol; close this connection only."""


class AuthenticationError(RemoteProtocolError):
    """The peer failed the challenge-response authentication."""


class RejectedMessageError(RemoteProtocolError):
    """Raised by an application's message handler to refuse a peer's message for good (it
    is invalid, or conflicts with what the peer said before): the message counts as delivered
    and the transport sends the peer a ``Reject`` with this reason, so it is never resent.
    Other handler errors are retried on the same connection, with backoff."""


class PeerRejectedError(ProtocolError):
    """The link was given up: the peer's application refused a message of ours (``Reject``,
    on a link that stops on a refusal) or the peer refused our credential."""


class PeerUnreachableError(PeerRejectedError):
    """The link was given up: no session with the peer within the client's give-up time
    (``TransportConfig.give_up_after``); the message says where, why and for how long."""


class PeerTimeoutError(ProtocolError):
    """The peer stayed silent past the idle timeout or the handshake deadline."""

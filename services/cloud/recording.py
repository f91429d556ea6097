"""An append-only recording of the uplink messages the cloud applied (opt-in, for replays).

``recslam cloud --record FILE`` appends one record per message that
:meth:`services.cloud.app.CloudApp.handle` applied, in the order the worker applied them,
so that an experiment can feed exactly the same input to differently configured clouds
(``recslam experiment table3``).

File layout: the 8-byte magic ``RSLREC1\\n``, then records, each a 4-byte big-endian length
followed by that many bytes of msgpack: the array ``[edge_id, stream_id, seq, type_id,
payload, t_recv]`` where ``payload`` is the message's protocol payload
(:func:`common.protocol.messages.encode_payload`, decoded again with ``decode_payload``) and
``t_recv`` the wall-clock receive time in seconds. Nothing is fsynced: a recording cut short
by a crash ends in a truncated record, which :func:`read_recording` reports (or, with
``allow_truncated_tail``, drops).
"""

from __future__ import annotations

import logging
import struct
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import msgpack

import common.links  # noqa: F401  (registers every link's message types for decoding)
from common.errors import RecslamError
from common.protocol.errors import ProtocolError
from common.protocol.messages import Message, decode_payload, encode_payload

log = logging.getLogger(__name__)

MAGIC = b"RSLREC1\n"
_LEN = struct.Struct(">I")
MAX_RECORD_BYTES = 256 * 1024 * 1024


class RecordingError(RecslamError):
    """A recording file is missing, not a recording, or holds a corrupt record."""


@dataclass(frozen=True)
class Record:
    """One applied uplink message.

    Attributes:
        edge_id: the edge's agent id (the connection's peer).
        stream_id: the edge link's stream id.
        seq: the message's sequence number on that stream.
        message: the decoded message.
        t_recv: wall-clock time the cloud received it, seconds since the epoch.
        offset: byte offset of the record in the file.
    """

    edge_id: str
    stream_id: bytes
    seq: int
    message: Message
    t_recv: float
    offset: int = 0


class RecordingWriter:
    """Appends records to ``path`` (created with the magic when new or empty).

    Not thread-safe: the cloud service writes from its single worker thread."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f: BinaryIO = self.path.open("ab")
        if self._f.tell() == 0:
            self._f.write(MAGIC)
        self.records = 0
        log.info("recording uplink messages to %s", self.path)

    def write(
        self,
        edge_id: str,
        stream_id: bytes,
        seq: int,
        message: Message,
        t_recv: float | None = None,
    ) -> None:
        """Append one message (its protocol payload; ``t_recv`` defaults to now)."""
        body = msgpack.packb(
            [
                edge_id,
                bytes(stream_id),
                int(seq),
                int(message.TYPE_ID),
                encode_payload(message),
                float(time.time() if t_recv is None else t_recv),
            ],
            use_bin_type=True,
        )
        self._f.write(_LEN.pack(len(body)) + body)
        self.records += 1

    def flush(self) -> None:
        self._f.flush()

    def close(self) -> None:
        if not self._f.closed:
            self._f.close()
            log.info("recording %s closed: %d records", self.path, self.records)

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _decode(body: bytes, path: Path, offset: int) -> Record:
    def bad(why: str) -> RecordingError:
        return RecordingError(f"{path}: corrupt record at offset {offset}: {why}")

    try:
        values = msgpack.unpackb(body, raw=False, use_list=True)
    except (
        ValueError,
        TypeError,
        msgpack.ExtraData,
        msgpack.FormatError,
        msgpack.StackError,
        UnicodeDecodeError,
    ) as exc:
        raise bad(f"undecodable msgpack ({exc})") from None
    if not isinstance(values, list) or len(values) != 6:
        raise bad("expected an array of 6 fields")
    edge_id, stream_id, seq, type_id, payload, t_recv = values
    if not (
        isinstance(edge_id, str)
        and isinstance(stream_id, bytes)
        and isinstance(seq, int)
        and isinstance(type_id, int)
        and isinstance(payload, bytes)
        and isinstance(t_recv, float | int)
    ):
        raise bad("field of the wrong type")
    try:
        message = decode_payload(type_id, payload)
    except ProtocolError as exc:
        raise bad(str(exc)) from None
    return Record(edge_id, stream_id, seq, message, float(t_recv), offset)


def read_recording(path: str | Path, allow_truncated_tail: bool = False) -> Iterator[Record]:
    """Yield the records of ``path`` in order.

    Raises :class:`RecordingError` naming the file and the record's byte offset for a corrupt
    record; a truncated last record is dropped with a warning when ``allow_truncated_tail``
    (a recording of a cloud that was killed), an error otherwise."""
    path = Path(path)
    try:
        f = path.open("rb")
    except OSError as exc:
        raise RecordingError(f"{path}: cannot open recording ({exc})") from None
    with f:
        if f.read(len(MAGIC)) != MAGIC:
            raise RecordingError(f"{path}: not an uplink recording (bad magic at offset 0)")
        offset = len(MAGIC)
        while True:
            head = f.read(_LEN.size)
            if not head:
                return
            n = _LEN.unpack(head)[0] if len(head) == _LEN.size else -1
            if n > MAX_RECORD_BYTES:
                raise RecordingError(
                    f"{path}: corrupt record at offset {offset}: length {n} out of range"
                )
            body = f.read(n) if n >= 0 else b""
            if n < 0 or len(body) < n:
                msg = f"{path}: truncated record at offset {offset}"
                if allow_truncated_tail:
                    log.warning("%s (dropped)", msg)
                    return
                raise RecordingError(msg)
            yield _decode(body, path, offset)
            offset += _LEN.size + n

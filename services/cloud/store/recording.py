"""An append-only recording of the uplink messages the cloud applied (opt-in, for replays).

``recslam cloud --record FILE`` appends one record per message that
:meth:`services.cloud.app.CloudApp.handle` applied, in the order the worker applied them,
so that an experiment can feed exactly the same input to differently configured clouds
(``recslam experiment table3``).

It also records the cloud's schedule as it ran (version 2): every call the service made on
its :class:`~services.cloud.core.CloudCore` besides ``handle`` (a timer round, a solve
handed back, the shutdown ...) as a :class:`Step`, in the order the worker made them, so that
a replay can drive the core through the very same schedule (:mod:`lab.table3`).

File layout: an 8-byte magic, then records, each a 4-byte big-endian length followed by that
many bytes of msgpack.

- Version 2 (magic ``RSLREC2\\n``): a message is the array ``[edge_id, stream_id, seq,
  type_id, payload, t_recv, t_core]``, where ``payload`` is the message's protocol payload
  (:func:`common.protocol.messages.encode_payload`, decoded again with ``decode_payload``),
  ``t_recv`` the wall-clock receive time in seconds and ``t_core`` the ``now`` the core was
  given with it (the service's monotonic clock, seconds; nil if unknown); a step is the array
  ``[0, name, now, args]`` (:data:`STEP_NAMES`).
- Version 1 (magic ``RSLREC1\\n``, recordings made before the schedule was recorded): messages
  only, ``[edge_id, stream_id, seq, type_id, payload, t_recv]``. Still read; a writer
  appending to such a file keeps its version (and records no steps).

Nothing is fsynced: a recording cut short by a crash ends in a truncated record, which
:func:`read_recording` reports (or, with ``allow_truncated_tail``, drops).
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

MAGIC_V1 = b"RSLREC1\n"
MAGIC = b"RSLREC2\n"
STEP_NAMES = frozenset(
    {
        "timer",
        "optimize",
        "full_ba",
        "flush",
        "shutdown",
        "cancel",
        "request",
        "solved",
        "failed",
        "load",
    }
)
"""The core calls a step records: a round started (``timer``: ``on_timer``; ``optimize``
[map]; ``full_ba`` [map, max_seconds, send]; ``flush``; ``shutdown``), ``cancel``, a solve the
core asked for (``request`` [kind, map]) and its hand-back (``solved`` / ``failed`` [kind,
map]), and a ``load`` [busy] that changed whether the core is overloaded (``CloudCore.load``,
recorded after the message it followed)."""
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
    t_core: float | None = None
    """The ``now`` the service's core was given with the message (version 2; None before)."""


@dataclass(frozen=True)
class Step:
    """One call the service made on its core besides ``handle`` (:data:`STEP_NAMES`):
    ``name``, the core's ``now`` and the call's arguments (``args``)."""

    name: str
    now: float
    args: tuple[object, ...] = ()
    offset: int = 0


class RecordingWriter:
    """Appends records to ``path`` (created with the magic when new or empty).

    Not thread-safe: the cloud service writes from its single worker thread."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f: BinaryIO = self.path.open("ab")
        self.version = 2
        if self._f.tell() == 0:
            self._f.write(MAGIC)
        else:
            with self.path.open("rb") as head:
                if head.read(len(MAGIC)) == MAGIC_V1:
                    self.version = 1
                    log.info("%s is a version-1 recording: appending without steps", path)
        self.records = 0
        log.info("recording uplink messages to %s", self.path)

    def write(
        self,
        edge_id: str,
        stream_id: bytes,
        seq: int,
        message: Message,
        t_recv: float | None = None,
        t_core: float | None = None,
    ) -> None:
        """Append one message (its protocol payload; ``t_recv`` defaults to now; ``t_core``:
        the core's ``now`` with it)."""
        fields: list[object] = [
            edge_id,
            bytes(stream_id),
            int(seq),
            int(message.TYPE_ID),
            encode_payload(message),
            float(time.time() if t_recv is None else t_recv),
        ]
        if self.version >= 2:
            fields.append(None if t_core is None else float(t_core))
        self._append(fields)

    def write_step(self, name: str, now: float, args: tuple[object, ...] = ()) -> None:
        """Append one step (a core call, :data:`STEP_NAMES`); none in a version-1 file."""
        if name not in STEP_NAMES:
            raise ValueError(f"unknown recording step {name!r}")
        if self.version >= 2:
            self._append([0, name, float(now), list(args)])

    def _append(self, fields: list[object]) -> None:
        body = msgpack.packb(fields, use_bin_type=True)
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


def _decode(body: bytes, path: Path, offset: int, version: int) -> Record | Step:
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
    if not isinstance(values, list):
        raise bad("not an array")
    if version >= 2 and len(values) == 4 and values[0] == 0:
        _, name, now, args = values
        if name not in STEP_NAMES or not isinstance(now, float | int) or not isinstance(args, list):
            raise bad(f"malformed step {values[:3]!r}")
        return Step(name, float(now), tuple(args), offset)
    n_fields = 7 if version >= 2 else 6
    if len(values) != n_fields:
        raise bad(f"expected an array of {n_fields} fields")
    edge_id, stream_id, seq, type_id, payload, t_recv = values[:6]
    t_core = values[6] if version >= 2 else None
    if not (
        isinstance(edge_id, str)
        and isinstance(stream_id, bytes)
        and isinstance(seq, int)
        and isinstance(type_id, int)
        and isinstance(payload, bytes)
        and isinstance(t_recv, float | int)
        and (t_core is None or isinstance(t_core, float | int))
    ):
        raise bad("field of the wrong type")
    try:
        message = decode_payload(type_id, payload)
    except ProtocolError as exc:
        raise bad(str(exc)) from None
    core_t = None if t_core is None else float(t_core)
    return Record(edge_id, stream_id, seq, message, float(t_recv), offset, core_t)


def has_schedule(path: str | Path) -> bool:
    """``path`` is a version-2 recording (it holds the service's schedule, :class:`Step`)."""
    try:
        with Path(path).open("rb") as f:
            return f.read(len(MAGIC)) == MAGIC
    except OSError as exc:
        raise RecordingError(f"{path}: cannot open recording ({exc})") from None


def read_recording(path: str | Path, allow_truncated_tail: bool = False) -> Iterator[Record]:
    """Yield the message records of ``path`` in order (steps left out).

    Raises :class:`RecordingError` naming the file and the record's byte offset for a corrupt
    record; a truncated last record is dropped with a warning when ``allow_truncated_tail``
    (a recording of a cloud that was killed), an error otherwise."""
    for entry in read_schedule(path, allow_truncated_tail):
        if isinstance(entry, Record):
            yield entry


def read_schedule(path: str | Path, allow_truncated_tail: bool = False) -> Iterator[Record | Step]:
    """Yield the messages and steps of ``path`` in order (as :func:`read_recording`)."""
    path = Path(path)
    try:
        f = path.open("rb")
    except OSError as exc:
        raise RecordingError(f"{path}: cannot open recording ({exc})") from None
    with f:
        magic = f.read(len(MAGIC))
        if magic not in (MAGIC, MAGIC_V1):
            raise RecordingError(f"{path}: not an uplink recording (bad magic at offset 0)")
        version = 2 if magic == MAGIC else 1
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
            yield _decode(body, path, offset, version)
            offset += _LEN.size + n

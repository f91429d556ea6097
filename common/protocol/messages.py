"""Every message type of the wire protocol, in one module, with stable type ids.

A message is a frozen dataclass registered with :func:`message` under a type id that never
changes once released. Its payload on the wire is the msgpack array of its field values in
declaration order; bulk data (features, descriptors, images of arrays) travels as ``bytes``
(msgpack bin), never as lists of numbers. Field values are checked against the annotations
when encoding (wrong type: :class:`LocalProtocolError`) and when decoding (wrong type from a
peer: :class:`RemoteProtocolError`).

Supported field annotations: ``int``, ``float``, ``bool``, ``str``, ``bytes``, ``X | None``,
``tuple[X, ...]``, ``tuple[X, Y, ...fixed]``, ``dict[str, X]`` and nested frozen dataclasses
whose fields use the same annotations (encoded as arrays).

Type id ranges (stable; add, never renumber):

- ``0x0001-0x00FF`` control messages of the session (handshake, ack, heartbeat, close);
- ``0x0100-0x01FF`` generic application messages (:class:`Blob`, used by tests/benchmarks);
- ``0x0200-0x02FF`` robot -> edge; ``0x0300-0x03FF`` edge -> robot;
- ``0x0400-0x04FF`` edge -> cloud; ``0x0500-0x05FF`` cloud -> edge.

``SCHEMA_VERSION`` is exchanged in the handshake; bump it when a released message changes.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Callable
from typing import Any, ClassVar, TypeVar, dataclass_transform

import msgpack

from common.protocol.errors import LocalProtocolError, ProtocolError, RemoteProtocolError

SCHEMA_VERSION = 7
"""2: the coded link messages (0x0302, 0x0405-0x0407, 0x0502) exist; a schema-1 peer would not
know them, so it is refused at the handshake with a clear reason. 3: a robot's stream starts
with its sensors (``RobotSensors`` 0x0203, forwarded as ``AgentSensors`` 0x0408); a schema-2
robot would send none, and a schema-2 edge or cloud would not know them. 4: the edge's coded
keyframe states and map points name the frame they are in (``FrameAnchor``, body version 2); a
schema-3 cloud would refuse each of them. 5: the edge tells a robot its camera-IMU time offset
(``CameraImuOffset`` 0x0303) and ``AgentStatus`` carries a ``detail`` and the offset the cloud
reads the robot's IMU with (``time_offset_ns``). 6: the edge sends a robot its pose at every
frame (``FramePose`` 0x0304) and the cloud the frames' poses relative to their keyframes
(``FramePoses`` 0x0409); a schema-5 robot or cloud would not know them. 7: ``FramePose.status``
is an index into ``common.links.robot_edge.POSE_STATUSES``, not the name."""
CONTROL_MAX_TYPE_ID = 0x00FF

_Converter = Callable[[Any, str], Any]


class _FieldTypeError(ProtocolError):
    """Internal: a value does not match its annotation (re-raised with blame attached)."""


class Message:
    """Base class of all wire messages (see :func:`message`)."""

    TYPE_ID: ClassVar[int]
    CONTROL: ClassVar[bool]
    _fields_spec: ClassVar[tuple[tuple[str, _Converter, _Converter], ...]]


_REGISTRY: dict[int, type[Message]] = {}

M = TypeVar("M", bound=Message)


@dataclass_transform(frozen_default=True)
def message(type_id: int) -> Callable[[type[M]], type[M]]:
    """Class decorator: make a frozen, slotted dataclass and register it under ``type_id``."""

    def wrap(cls: type[M]) -> type[M]:
        if not 1 <= type_id <= 0xFFFF:
            raise ValueError(f"type id {type_id} out of range 1..65535")
        if type_id in _REGISTRY:
            raise ValueError(f"type id 0x{type_id:04x} already used by {_REGISTRY[type_id]}")
        dc = dataclasses.dataclass(frozen=True, slots=True)(cls)
        dc.TYPE_ID = type_id
        dc.CONTROL = type_id <= CONTROL_MAX_TYPE_ID
        dc._fields_spec = _compile_fields(dc)
        _REGISTRY[type_id] = dc
        return dc

    return wrap


def message_class(type_id: int) -> type[Message]:
    """Return the class registered under ``type_id`` (RemoteProtocolError if unknown)."""
    try:
        return _REGISTRY[type_id]
    except KeyError:
        raise RemoteProtocolError(f"unknown message type 0x{type_id:04x}") from None


def registered_types() -> dict[int, type[Message]]:
    """A copy of the type-id registry."""
    return dict(_REGISTRY)


def encode_payload(msg: Message) -> bytes:
    """msgpack payload of ``msg``; LocalProtocolError if a field has the wrong type."""
    try:
        values = [enc(getattr(msg, name), name) for name, enc, _ in msg._fields_spec]
    except _FieldTypeError as exc:
        raise LocalProtocolError(f"{type(msg).__name__}: {exc}") from None
    return msgpack.packb(values, use_bin_type=True)


def _no_ext(code: int, data: bytes) -> Any:
    raise _FieldTypeError(f"msgpack ext type {code} not allowed")


def decode_payload(type_id: int, payload: bytes) -> Message:
    """Decode and type-check a payload; every failure is a RemoteProtocolError."""
    cls = message_class(type_id)
    name = cls.__name__
    try:
        values = msgpack.unpackb(
            payload, raw=False, use_list=True, strict_map_key=True, ext_hook=_no_ext
        )
    except _FieldTypeError as exc:
        raise RemoteProtocolError(f"{name}: {exc}") from None
    except (
        ValueError,
        TypeError,
        msgpack.ExtraData,
        msgpack.FormatError,
        msgpack.StackError,
        UnicodeDecodeError,
        RecursionError,
    ) as exc:
        raise RemoteProtocolError(f"{name}: undecodable msgpack payload ({exc})") from None
    spec = cls._fields_spec
    if not isinstance(values, list) or len(values) != len(spec):
        raise RemoteProtocolError(f"{name}: payload must be an array of {len(spec)} fields")
    try:
        kwargs = {fname: dec(v, fname) for (fname, _, dec), v in zip(spec, values, strict=True)}
    except _FieldTypeError as exc:
        raise RemoteProtocolError(f"{name}: {exc}") from None
    return cls(**kwargs)


# ----------------------------------------------------------------------------- converters
def _compile_fields(cls: type) -> tuple[tuple[str, _Converter, _Converter], ...]:
    hints = typing.get_type_hints(cls)
    return tuple(
        (f.name, _converter(hints[f.name], encode=True), _converter(hints[f.name], encode=False))
        for f in dataclasses.fields(cls)
    )


def _converter(tp: Any, *, encode: bool) -> _Converter:
    if tp is bool:
        return _scalar(bool, "bool")
    if tp is int:

        def conv_int(v: Any, path: str) -> int:
            if type(v) is not int or not -(2**63) <= v < 2**64:
                raise _FieldTypeError(f"{path}: expected int (64-bit), got {type(v).__name__}")
            return v

        return conv_int
    if tp is float:

        def conv_float(v: Any, path: str) -> float:
            if type(v) is float:
                return v
            if type(v) is int and not encode:
                raise _FieldTypeError(f"{path}: expected float, got int")
            if type(v) is int:
                return float(v)
            raise _FieldTypeError(f"{path}: expected float, got {type(v).__name__}")

        return conv_float
    if tp is str:
        return _scalar(str, "str")
    if tp is bytes:

        def conv_bytes(v: Any, path: str) -> bytes:
            if type(v) is bytes:
                return v
            if encode and isinstance(v, bytearray | memoryview):
                return bytes(v)
            raise _FieldTypeError(f"{path}: expected bytes, got {type(v).__name__}")

        return conv_bytes
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (types.UnionType, typing.Union) and len(args) == 2 and type(None) in args:
        inner = _converter(next(a for a in args if a is not type(None)), encode=encode)

        def conv_opt(v: Any, path: str) -> Any:
            return None if v is None else inner(v, path)

        return conv_opt
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            item = _converter(args[0], encode=encode)

            def conv_var(v: Any, path: str) -> Any:
                if not isinstance(v, list | tuple):
                    raise _FieldTypeError(f"{path}: expected array, got {type(v).__name__}")
                out = tuple(item(x, f"{path}[{i}]") for i, x in enumerate(v))
                return list(out) if encode else out

            return conv_var
        items = [_converter(a, encode=encode) for a in args]

        def conv_fixed(v: Any, path: str) -> Any:
            if not isinstance(v, list | tuple) or len(v) != len(items):
                raise _FieldTypeError(f"{path}: expected array of {len(items)}")
            out = tuple(c(x, f"{path}[{i}]") for i, (c, x) in enumerate(zip(items, v, strict=True)))
            return list(out) if encode else out

        return conv_fixed
    if origin is dict and args and args[0] is str:
        val = _converter(args[1], encode=encode)

        def conv_dict(v: Any, path: str) -> Any:
            if not isinstance(v, dict):
                raise _FieldTypeError(f"{path}: expected map, got {type(v).__name__}")
            out = {}
            for k, x in v.items():
                if type(k) is not str:
                    raise _FieldTypeError(f"{path}: map keys must be str")
                out[k] = val(x, f"{path}[{k!r}]")
            return out

        return conv_dict
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        hints = typing.get_type_hints(tp)
        subs = [(f.name, _converter(hints[f.name], encode=encode)) for f in dataclasses.fields(tp)]

        def conv_struct(v: Any, path: str) -> Any:
            if encode:
                if not isinstance(v, tp):
                    raise _FieldTypeError(f"{path}: expected {tp.__name__}")
                return [c(getattr(v, n), f"{path}.{n}") for n, c in subs]
            if not isinstance(v, list) or len(v) != len(subs):
                raise _FieldTypeError(f"{path}: expected {tp.__name__} as array of {len(subs)}")
            return tp(**{n: c(x, f"{path}.{n}") for (n, c), x in zip(subs, v, strict=True)})

        return conv_struct
    raise TypeError(f"unsupported field annotation {tp!r}")


def _scalar(kind: type, label: str) -> _Converter:
    def conv(v: Any, path: str) -> Any:
        if type(v) is not kind:
            raise _FieldTypeError(f"{path}: expected {label}, got {type(v).__name__}")
        return v

    return conv


# ------------------------------------------------------------------------ control messages
@message(0x0001)
class Hello(Message):
    """Client -> server, first frame. Carries the client's resume position for both streams.

    ``out_stream_id``/``first_unacked``: identity of the client's outgoing stream and the
    lowest sequence still in its outbox; ``in_stream_id``/``last_delivered``: the server
    stream the client has delivered from (empty if none) and the last sequence delivered.
    """

    protocol_version: int
    schema_version: int
    role: str
    agent_id: str
    nonce: bytes
    out_stream_id: bytes
    first_unacked: int
    in_stream_id: bytes
    last_delivered: int
    window_messages: int
    window_bytes: int


@message(0x0002)
class Challenge(Message):
    """Server -> client: server identity, server nonce and the server's proof of the secret."""

    protocol_version: int
    schema_version: int
    role: str
    agent_id: str
    nonce: bytes
    mac: bytes


@message(0x0003)
class Auth(Message):
    """Client -> server: the client's proof of the secret over the whole transcript."""

    mac: bytes


@message(0x0004)
class Welcome(Message):
    """Server -> client after successful authentication: the server's resume position."""

    out_stream_id: bytes
    first_unacked: int
    in_stream_id: bytes
    last_delivered: int
    window_messages: int
    window_bytes: int


@message(0x0005)
class Ack(Message):
    """Explicit acknowledgement; the cumulative ack is in the frame header."""


@message(0x0006)
class Heartbeat(Message):
    """Keep-alive sent when the link is otherwise idle (also carries the header ack)."""


@message(0x0007)
class Close(Message):
    """Orderly close with a reason (code: see ``CloseCode`` in session.py)."""

    code: int
    reason: str


@message(0x0008)
class Reject(Message):
    """Receiver -> sender: the receiving application refused message ``seq`` for good (its
    handler raised ``RejectedMessageError``). The message counts as delivered and is never
    redelivered; the sender learns why, and its application decides to skip or to stop."""

    seq: int
    reason: str


# -------------------------------------------------------------------- application messages
@message(0x0100)
class Blob(Message):
    """Generic application message: opaque bytes on a numbered channel.

    Used by the protocol tests and ``benchmarks/bench_protocol.py``; services define their
    own typed messages in the ranges above instead of packing everything into blobs.
    """

    channel: int
    data: bytes


# ------------------------------------------------------------------------ link messages
# The messages of each link live in that link's module with their encoders and decoders
# (``common.links.robot_edge``, ``common.links.edge_cloud``); ``import common.links``
# registers all of them.

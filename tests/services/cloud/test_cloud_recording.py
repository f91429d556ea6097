"""The uplink recording: round trip, corrupt and truncated records."""

from __future__ import annotations

import struct

import msgpack
import numpy as np
import pytest

from common.links.edge_cloud import AgentStatus, CullEvent
from common.protocol.arrays import pack_array
from common.protocol.messages import encode_payload
from services.cloud.store.recording import (
    MAGIC,
    MAGIC_V1,
    RecordingError,
    RecordingWriter,
    Step,
    has_schedule,
    read_recording,
    read_schedule,
)


def _write(path) -> list[int]:
    """Three records; returns the file size after each."""
    sizes = []
    with RecordingWriter(path) as w:
        w.write("edge-a", b"s1", 1, AgentStatus("robot0", 0, "tracking", 10, 2, 0, {"tx": 5}), 1.5)
        w.flush()
        sizes.append(path.stat().st_size)
        cull = CullEvent("robot0", 0, pack_array(np.array([3, 4]), "<i8"), b"")
        w.write("edge-a", b"s1", 2, cull, 2.5)
        w.flush()
        sizes.append(path.stat().st_size)
        w.write("edge-b", b"s2", 1, CullEvent("robot1", 1, b"", b""), 3.0)
    sizes.append(path.stat().st_size)
    return sizes


def test_round_trip_keeps_order_fields_and_offsets(tmp_path):
    path = tmp_path / "uplink.rec"
    sizes = _write(path)
    recs = list(read_recording(path))
    assert [(r.edge_id, r.stream_id, r.seq, r.t_recv) for r in recs] == [
        ("edge-a", b"s1", 1, 1.5),
        ("edge-a", b"s1", 2, 2.5),
        ("edge-b", b"s2", 1, 3.0),
    ]
    assert recs[0].message == AgentStatus("robot0", 0, "tracking", 10, 2, 0, {"tx": 5})
    assert np.frombuffer(recs[1].message.keyframe_ids, "<i8").tolist() == [3, 4]
    assert [r.offset for r in recs] == [len(MAGIC), sizes[0], sizes[1]]
    # Appending to an existing recording continues it (no second magic).
    with RecordingWriter(path) as w:
        w.write("edge-a", b"s1", 3, CullEvent("robot0", 0, b"", b""), 4.0)
    assert [r.seq for r in read_recording(path)] == [1, 2, 1, 3]


def test_corrupt_record_names_file_and_offset(tmp_path):
    path = tmp_path / "uplink.rec"
    sizes = _write(path)
    data = bytearray(path.read_bytes())
    data[sizes[0] + 4 : sizes[0] + 12] = b"\xc1" * 8  # 0xc1: never used in msgpack
    path.write_bytes(bytes(data))
    it = read_recording(path)
    assert next(it).seq == 1
    with pytest.raises(RecordingError, match=rf"{path}: corrupt record at offset {sizes[0]}"):
        next(it)


def test_truncated_tail_is_an_error_or_dropped(tmp_path):
    path = tmp_path / "uplink.rec"
    sizes = _write(path)
    path.write_bytes(path.read_bytes()[: sizes[2] - 3])
    with pytest.raises(RecordingError, match=rf"truncated record at offset {sizes[1]}"):
        list(read_recording(path))
    assert [r.seq for r in read_recording(path, allow_truncated_tail=True)] == [1, 2]


def test_not_a_recording(tmp_path):
    path = tmp_path / "other.bin"
    path.write_bytes(b"hello world")
    with pytest.raises(RecordingError, match="not an uplink recording"):
        list(read_recording(path))
    with pytest.raises(RecordingError, match="cannot open"):
        list(read_recording(tmp_path / "missing.rec"))


def test_cloud_server_records_every_applied_message(tmp_path):
    import asyncio

    from common.protocol import SessionConfig
    from common.transport import Delivery
    from common.vocabulary import Vocabulary
    from services.cloud.server import CloudServer
    from services.cloud.service_config import CloudServiceConfig, ProcessConfig, StoreConfig
    from sim.cloud import default_camera

    cfg = CloudServiceConfig(
        store=StoreConfig(output_every_s=0), processes=ProcessConfig(optimizer_process=False)
    )
    session = SessionConfig("cloud", "cloud", b"0123456789abcdef0123")
    rec = tmp_path / "uplink.rec"
    msgs = [AgentStatus("robot0", 0, "tracking", i, 0, 0, {}) for i in (1, 2)]

    async def main() -> None:
        cloud = CloudServer(
            session, tmp_path / "state", default_camera(), Vocabulary.load(), cfg, record=rec
        )
        await cloud.start("127.0.0.1", 0)
        try:
            for seq, m in enumerate(msgs, 1):
                await cloud._on_message(Delivery("edge-a", "edge", m, seq, b"stream"))
        finally:
            await cloud.stop(write_output=False)

    asyncio.run(main())
    recs = list(read_recording(rec))
    assert [(r.edge_id, r.seq, r.message) for r in recs] == [
        ("edge-a", 1, msgs[0]),
        ("edge-a", 2, msgs[1]),
    ]


def test_steps_travel_in_order_and_version_1_recordings_still_read(tmp_path):
    path = tmp_path / "v2.rec"
    with RecordingWriter(path) as w:
        w.write("edge", b"s", 1, CullEvent("robot0", 0, b"", b""), 10.0, 1.25)
        w.write_step("timer", 1.5)
        w.write_step("request", 1.5, ("pose graph", 0))
        w.write("edge", b"s", 2, CullEvent("robot0", 0, b"", b""), 10.5, 1.75)
        w.write_step("solved", 2.0, ("pose graph", 0))
        with pytest.raises(ValueError, match="unknown recording step 'nap'"):
            w.write_step("nap", 2.0)
    assert has_schedule(path)
    entries = list(read_schedule(path))
    assert [type(e).__name__ for e in entries] == ["Record", "Step", "Step", "Record", "Step"]
    assert entries[2] == Step("request", 1.5, ("pose graph", 0), entries[2].offset)
    assert [r.t_core for r in read_recording(path)] == [1.25, 1.75]  # messages only

    # A recording made before steps were recorded (version 1): read, no t_core, no steps;
    # a writer appending to it keeps its version.
    old = tmp_path / "v1.rec"
    body = msgpack.packb(
        ["edge", b"s", 1, CullEvent.TYPE_ID, encode_payload(CullEvent("r", 0, b"", b"")), 3.0],
        use_bin_type=True,
    )
    old.write_bytes(MAGIC_V1 + struct.pack(">I", len(body)) + body)
    assert not has_schedule(old)
    with RecordingWriter(old) as w:
        w.write("edge", b"s", 2, CullEvent("r", 0, b"", b""), 4.0, 9.0)
        w.write_step("timer", 9.5)
    got = list(read_schedule(old))
    assert [(r.seq, r.t_recv, r.t_core) for r in got] == [(1, 3.0, None), (2, 4.0, None)]

    # A damaged step names its offset.
    bad = tmp_path / "bad.rec"
    step = msgpack.packb([0, "timer", "soon", []], use_bin_type=True)
    bad.write_bytes(MAGIC + struct.pack(">I", len(step)) + step)
    with pytest.raises(RecordingError, match=f"offset {len(MAGIC)}: malformed step"):
        list(read_schedule(bad))

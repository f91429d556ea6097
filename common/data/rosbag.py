"""ROS bags as sequences: ROS 1 ``.bag`` files and ROS 2 bag folders, read with ``rosbags``
(``rosbags.highlevel.AnyReader`` handles both).

A :class:`BagSequence` yields what :class:`~common.data.euroc.EurocSequence` yields for the
same recording: frame timestamps in int64 ns, uint8 (H, W) grayscale images and
:class:`~common.data.euroc.ImuBatch` samples (``(t[i-1], t[i]]`` per frame, the same rule,
:func:`~common.data.euroc.frames_with_imu`), so the robot does not know which it plays.

- Times are the messages' ``header.stamp`` (sensor time), not the recording time; a message
  with a zero stamp takes its recording time. Image stamps must increase in recording order;
  IMU messages are sorted by stamp (duplicates are an error).
- Images: ``sensor_msgs/msg/Image`` in ``mono8`` / ``8UC1``, ``mono16`` / ``16UC1`` (high
  byte, as OpenCV reads a 16-bit PNG), ``bgr8``, ``rgb8``, ``bgra8``, ``rgba8`` (colour to
  gray with OpenCV's weights), or ``sensor_msgs/msg/CompressedImage`` (decoded to gray).
  IMU: ``sensor_msgs/msg/Imu`` (angular velocity rad/s, linear acceleration m/s², IMU frame).
- A bag holds no calibration: one is given (:mod:`common.data.calibration_files`); its
  Kalibr ``rostopic`` entries name the default topics.

Every problem raises :class:`BagError` naming the bag and the topic.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.interfaces import Connection

from common.data.calibration_files import SensorCalibration
from common.data.euroc import (
    EurocFrame,
    ImuBatch,
    check_image_size,
    frames_with_imu,
    timeline_rate,
    timeline_summary,
)
from common.errors import RecslamError

logger = logging.getLogger(__name__)

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
IMU_TYPES = ("sensor_msgs/msg/Imu",)
IMAGE_ENCODINGS: dict[str, tuple[int, int | None]] = {
    "mono8": (1, None),
    "8UC1": (1, None),
    "mono16": (1, None),
    "16UC1": (1, None),
    "bgr8": (3, cv2.COLOR_BGR2GRAY),
    "rgb8": (3, cv2.COLOR_RGB2GRAY),
    "bgra8": (4, cv2.COLOR_BGRA2GRAY),
    "rgba8": (4, cv2.COLOR_RGBA2GRAY),
}
"""``Image.encoding`` -> (channels, OpenCV conversion to gray). 16-bit images keep their high
byte, as OpenCV's reading of a 16-bit PNG as gray does (TUM-VI's ``_16`` recordings)."""


class BagError(RecslamError):
    """A bag is missing, unreadable, lacks a topic, or holds unusable messages."""


def is_bag(path: Path | str) -> bool:
    """A ROS 1 ``.bag`` file or a ROS 2 bag folder (``metadata.yaml`` inside)."""
    path = Path(path)
    return (path.is_file() and path.suffix == ".bag") or (path / "metadata.yaml").is_file()


@contextlib.contextmanager
def open_bag(path: Path | str) -> Iterator[AnyReader]:
    """``with open_bag(p) as reader``: an opened reader, closed on exit."""
    path = Path(path)
    if not path.exists():
        raise BagError(f"{path}: no such bag")
    if not is_bag(path):
        raise BagError(f"{path}: not a ROS bag (a ROS 1 .bag file or a ROS 2 bag folder)")
    reader = AnyReader([path])
    try:
        reader.open()
    except (AnyReaderError, OSError, ValueError) as e:
        raise BagError(f"{path}: unreadable bag: {e}") from None
    try:
        yield reader
    finally:
        reader.close()


def stamp_ns(msg: Any, recorded_ns: int) -> int:
    """A message's ``header.stamp`` in ns (its recording time if the stamp is zero)."""
    t = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
    return t if t else recorded_ns


def _connection(reader: AnyReader, bag: Path, topic: str, types: tuple[str, ...]) -> Connection:
    conns = [c for c in reader.connections if c.topic == topic]
    if not conns:
        have = ", ".join(f"{c.topic} ({c.msgtype})" for c in reader.connections) or "none"
        raise BagError(f"{bag}: no topic {topic!r} (topics: {have})")
    conn = conns[0]
    if conn.msgtype not in types:
        raise BagError(
            f"{bag}: topic {topic!r} holds {conn.msgtype}, expected {' or '.join(types)}"
        )
    if len(conns) > 1:
        logger.info("%s: topic %s has %d connections; the first is read", bag, topic, len(conns))
    return conn


def image_to_gray(msg: Any, msgtype: str, where: str) -> np.ndarray:
    """uint8 (H, W) grayscale of an Image / CompressedImage message (BagError if unusable)."""
    if msgtype == "sensor_msgs/msg/CompressedImage":
        gray = cv2.imdecode(np.asarray(msg.data, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
        if gray is None:
            raise BagError(f"{where}: compressed image ({msg.format!r}) does not decode")
        return gray
    encoding = str(msg.encoding)
    if encoding not in IMAGE_ENCODINGS:
        raise BagError(
            f"{where}: image encoding {encoding!r} not supported ({', '.join(IMAGE_ENCODINGS)})"
        )
    channels, conversion = IMAGE_ENCODINGS[encoding]
    depth = 2 if encoding in ("mono16", "16UC1") else 1
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8)
    if h < 1 or w < 1 or step < w * channels * depth or len(data) < h * step:
        raise BagError(
            f"{where}: image of {w}x{h} {encoding} with step {step} has {len(data)} bytes"
        )
    rows = data[: h * step].reshape(h, step)[:, : w * channels * depth]
    if depth == 2:
        dtype = ">u2" if int(msg.is_bigendian) else "<u2"
        pixels16 = np.ascontiguousarray(rows).view(dtype).reshape(h, w)
        return (pixels16 >> 8).astype(np.uint8)
    pixels = rows.reshape(h, w, channels)
    if conversion is None:
        return np.ascontiguousarray(pixels[:, :, 0])
    return cv2.cvtColor(np.ascontiguousarray(pixels), conversion)


def bag_summary(path: Path | str) -> dict[str, Any]:
    """Facts of a bag for ``recslam dataset info``: its topics (type, messages, duration [s]
    and rate [Hz] over their recording times) and the bag's span."""
    path = Path(path)
    with open_bag(path) as reader:
        times: dict[int, list[int]] = {c.id: [] for c in reader.connections}
        for conn, t, _ in reader.messages():
            times[conn.id].append(t)
        topics = []
        for c in sorted(reader.connections, key=lambda c: c.topic):
            ts = np.array(times[c.id], dtype=np.int64)
            span = float(ts[-1] - ts[0]) * 1e-9 if len(ts) else 0.0
            topics.append(
                {
                    "topic": c.topic,
                    "type": c.msgtype,
                    "messages": len(ts),
                    "duration_s": span,
                    "rate_hz": timeline_rate(ts),
                }
            )
        return {
            "name": path.stem if path.is_file() else path.name,
            "path": str(path),
            "format": "ROS 2 bag" if reader.is2 else "ROS 1 bag",
            "messages": reader.message_count,
            "duration_s": reader.duration * 1e-9,
            "topics": topics,
        }


class BagSequence:
    """One camera + IMU recording in a bag, with a given calibration.

    Attributes as :class:`~common.data.euroc.EurocSequence`: ``name``, ``root`` (the bag),
    ``cam0``, ``cam1`` (None), ``imu``, ``calibration_info``, ``frame_timestamps_ns`` (N,)
    int64, ``imu_timestamps_ns`` (M,) int64, ``gyro`` (M, 3) rad/s, ``accel`` (M, 3) m/s²,
    ``groundtruth`` (None). Timestamps and IMU are read at once, images while iterating.
    """

    def __init__(
        self,
        path: Path | str,
        calibration: SensorCalibration,
        image_topic: str | None = None,
        imu_topic: str | None = None,
    ) -> None:
        self.root = Path(path).resolve()
        self.name = self.root.stem if self.root.is_file() else self.root.name
        image_topic = image_topic or calibration.image_topic
        imu_topic = imu_topic or calibration.imu_topic
        for option, topic in (("--image-topic", image_topic), ("--imu-topic", imu_topic)):
            if not topic:
                raise BagError(f"{self.root}: {option} is required (the calibration names none)")
        assert image_topic is not None and imu_topic is not None
        self.image_topic, self.imu_topic = image_topic, imu_topic
        with open_bag(self.root) as reader:
            image_conn = _connection(reader, self.root, image_topic, IMAGE_TYPES)
            imu_conn = _connection(reader, self.root, imu_topic, IMU_TYPES)
            imu = self._read_imu(reader, imu_conn)
            frame_ts = self._read_frame_stamps(reader, image_conn)
        shift_ns = round(calibration.timeshift_cam_imu_s * 1e9)
        frame_ts = frame_ts + shift_ns
        frame_ts.setflags(write=False)
        self._imu = imu
        self.frame_timestamps_ns: np.ndarray = frame_ts
        self.imu_timestamps_ns: np.ndarray = imu.timestamps_ns
        self.gyro: np.ndarray = imu.gyro
        self.accel: np.ndarray = imu.accel
        self.calibration_info = calibration.with_camera_rate(timeline_rate(frame_ts))
        self.cam0 = self.calibration_info.cam0
        self.cam1 = None
        self.imu = self.calibration_info.imu
        self.groundtruth = None
        logger.info(
            "%s: %d frames (%s), %d IMU samples (%s), %s",
            self.name,
            len(self),
            image_topic,
            len(imu),
            imu_topic,
            self.calibration_info.describe(),
        )

    def _read_imu(self, reader: AnyReader, conn: Connection) -> ImuBatch:
        rows: list[tuple[int, float, float, float, float, float, float]] = []
        for _, t, raw in reader.messages(connections=[conn]):
            m: Any = reader.deserialize(raw, conn.msgtype)
            w, a = m.angular_velocity, m.linear_acceleration
            rows.append((stamp_ns(m, t), w.x, w.y, w.z, a.x, a.y, a.z))
        if not rows:
            raise BagError(f"{self.root}: topic {conn.topic!r} has no messages")
        rows.sort(key=lambda r: r[0])
        ts = np.array([r[0] for r in rows], dtype=np.int64)
        values = np.array([r[1:] for r in rows], dtype=np.float64)
        dup = np.flatnonzero(np.diff(ts) == 0)
        if len(dup):
            raise BagError(f"{self.root}: topic {conn.topic!r}: duplicate stamp {ts[dup[0]]} ns")
        if not np.isfinite(values).all():
            raise BagError(f"{self.root}: topic {conn.topic!r}: a sample is not finite")
        return ImuBatch(ts, values[:, 0:3], values[:, 3:6])

    def _read_frame_stamps(self, reader: AnyReader, conn: Connection) -> np.ndarray:
        stamps = [
            stamp_ns(reader.deserialize(raw, conn.msgtype), t)
            for _, t, raw in reader.messages(connections=[conn])
        ]
        if not stamps:
            raise BagError(f"{self.root}: topic {conn.topic!r} has no messages")
        ts = np.array(stamps, dtype=np.int64)
        bad = np.flatnonzero(np.diff(ts) <= 0)
        if len(bad):
            i = int(bad[0]) + 1
            raise BagError(
                f"{self.root}: topic {conn.topic!r}: message {i} has stamp {ts[i]} ns, "
                f"not after the previous one's {ts[i - 1]} ns"
            )
        return ts

    def __len__(self) -> int:
        return len(self.frame_timestamps_ns)

    def __repr__(self) -> str:
        return f"BagSequence({str(self.root)!r}, {self.image_topic!r}, frames={len(self)})"

    @property
    def cameras(self) -> list[str]:
        return ["cam0"]

    def images(self, start: int = 0, stop: int | None = None) -> Iterator[np.ndarray]:
        """Decode images ``start..stop-1`` in order -> uint8 (H, W) grayscale (size checked
        against the calibration)."""
        stop = len(self) if stop is None else stop
        with open_bag(self.root) as reader:
            # a connection belongs to the reader that listed it: take this reader's own
            conn = _connection(reader, self.root, self.image_topic, IMAGE_TYPES)
            for i, (_, _, raw) in enumerate(reader.messages(connections=[conn])):
                if i >= stop:
                    return
                if i < start:
                    continue
                where = f"{self.root}: topic {conn.topic!r} message {i}"
                image = image_to_gray(reader.deserialize(raw, conn.msgtype), conn.msgtype, where)
                check_image_size(image, self.cam0, self.calibration_info, where)
                yield image

    def frames(
        self,
        start: int = 0,
        stop: int | None = None,
        load_images: bool = True,
        imu_lead_ns: int | Callable[[], int] = 0,
    ) -> Iterator[EurocFrame]:
        """Frames ``start..stop-1`` with their IMU batches (as ``EurocSequence.frames``)."""
        ts = self.frame_timestamps_ns
        stop = len(ts) if stop is None else stop
        if not 0 <= start <= stop <= len(ts):
            raise IndexError(f"frames({start}, {stop}) outside 0..{len(ts)}")
        images: Iterator[np.ndarray | None] = (
            self.images(start, stop) if load_images else iter([None] * (stop - start))
        )
        return frames_with_imu(ts, self._imu, start, stop, images, imu_lead_ns)

    def summary(self) -> dict[str, Any]:
        """The facts ``EurocSequence.summary`` gives, for a bag."""
        return {
            "name": self.name,
            "path": str(self.root),
            "frames": len(self),
            **timeline_summary(self.frame_timestamps_ns, self.imu_timestamps_ns),
            "cameras": self.cameras,
            "resolution": [self.cam0.width, self.cam0.height],
            "calibration": self.calibration_info.describe(),
            "has_groundtruth": False,
            "groundtruth_samples": 0,
        }

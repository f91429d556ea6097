"""The robot's core (sans-I/O): sensor input and the edge's messages in, work and messages out.

The events, jobs and actions are in :mod:`services.robot.core_events`. No sockets,
threads, locks, clock or files here (h11's rule): time enters as ``now``
(monotonic seconds) and every decision comes out as a value. The runner
(:mod:`services.robot.engine`) feeds :meth:`RobotCore.handle` with events from a driver, a
folder playback or the edge, runs the CPU work :meth:`RobotCore.next_job` hands it (tracking
and coding one frame, or applying the edge's feedback) on one worker thread, gives the result
back to :meth:`RobotCore.handle`, and does the :class:`Send` and :class:`PoseOut` actions.
:meth:`RobotCore.timer` / :meth:`RobotCore.on_timer` watch a stalled driver and an IMU that
is late for an image.

Frames and their IMU, one rule for every source (the folder's ``frames_with_imu``): an image
at camera time ``t`` is tracked with the IMU samples after the previous frame's up to and
including the first one at or after ``t + lead`` (``lead``: the camera-IMU offset the edge
found, when the IMU runs ahead). An image waits for that sample for at most
``imu_wait_s``; then it is tracked with what has come (counted, warned). A folder playback
therefore codes the very bytes it coded before this core existed.

Back-pressure: at most ``max_pending_images`` images wait for tracking; when a new one arrives
on a full queue, the oldest untracked one is dropped and counted (its IMU stays: it goes with
the next frame). A folder playback waits for room (:meth:`RobotCore.has_room`) instead, so it
never drops.

Live-input faults (each counted in :meth:`RobotCore.stats`, warned at its first occurrence
and then at most once per ``warn_interval_s``; never an exception, never a silent pose):

- an image whose time is not after the last accepted one (out of order, duplicate): dropped;
- an image more than ``clock_jump_s`` before the last one (the clock went back): dropped
  until the clock passes the last accepted time again (a clock reset needs a new stream:
  restart the robot);
- an image whose camera time ran ahead of the wall time since the last one by more than
  ``clock_jump_s`` (the clock jumped forward, or the driver lost a stretch): tracked, and its
  pose is flagged ``"clock_jump"``;
- an IMU sample not after the last one, or not finite: dropped; a hole between IMU samples
  longer than ``imu_gap_s``: kept, warned, and the poses of the frames whose IMU interval
  holds it are flagged ``"imu_gap"`` (the edge bridges it with its prior; the flag tells the
  user not to trust that stretch blindly);
- no image for ``stall_s`` while the robot waits for input (a stalled driver): warned once
  per stall, and again when images resume; likewise for the IMU;
- an image of the wrong size, type or encoding: dropped (the accepted encodings are
  :data:`ENCODINGS`; colour is converted to grey).
"""

from __future__ import annotations

import dataclasses
import logging
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from common.data.euroc import ImuBatch
from common.errors import RecslamError
from common.links.robot_edge import (
    CameraImuOffset,
    FramePose,
    InertialFeedback,
    InertialFeedbackCoded,
    MapPlacement,
)
from common.protocol.messages import Message
from services.robot.core_events import (
    Action,
    ApplyFeedback,
    EdgeInput,
    EndOfInput,
    Event,
    FrameDone,
    ImageInput,
    ImuInput,
    Job,
    LinkLoad,
    PoseOut,
    Send,
    TrackFrame,
)
from services.robot.poses import PoseTrack
from services.robot.uplink_budget import UplinkBudget

logger = logging.getLogger(__name__)

ENCODINGS = ("mono8", "8UC1", "mono16", "16UC1", "bgr8", "rgb8", "bgra8", "rgba8")
"""Raw image encodings the core accepts (ROS ``sensor_msgs/Image`` names)."""

FAULTS = (
    "image_invalid",
    "image_out_of_order",
    "image_duplicate",
    "clock_back",
    "clock_jump",
    "imu_out_of_order",
    "imu_invalid",
    "imu_gap",
    "imu_late",
    "image_stall",
    "imu_stall",
    "dropped_backpressure",
)
"""Kinds of live-input fault the core counts (see the module docstring)."""

FLAGS = ("imu_gap", "clock_jump", "imu_late")
"""Flags a pose may carry (:attr:`ReceivedPose.flags`): what the input did to its frame."""


class ImageError(RecslamError):
    """An image the robot cannot use (size, type or encoding)."""


@dataclass(frozen=True)
class LiveInputConfig:
    """How the robot takes live input (defaults fit a 20 Hz camera and a 200 Hz IMU).

    Attributes:
        max_pending_images: images waiting for tracking before the oldest is dropped (2: one
            being read while one is tracked; more only adds latency).
        imu_wait_s: longest wait [s] of an image for the IMU sample after it (0.25 s: 50
            samples at 200 Hz, far beyond a driver's jitter).
        imu_gap_s: a hole between IMU samples longer than this [s] is a gap (0.05 s: ten
            missed samples at 200 Hz).
        clock_jump_s: camera time running ahead of (or back from) wall time by more than this
            [s] between two images is a clock jump (0.5 s: ten frames at 20 Hz).
        stall_s: no image (or IMU sample) for this long [s] while the robot waits is a
            stalled driver (1 s).
        imu_keep_s: IMU kept [s] before the first image (the pre-roll; 10 s).
        warn_interval_s: a fault kind is warned at most once per this long [s] (5 s).
    """

    max_pending_images: int = 2
    imu_wait_s: float = 0.25
    imu_gap_s: float = 0.05
    clock_jump_s: float = 0.5
    stall_s: float = 1.0
    imu_keep_s: float = 10.0
    warn_interval_s: float = 5.0

    def __post_init__(self) -> None:
        if self.max_pending_images < 1:
            raise ValueError(f"max_pending_images must be >= 1, got {self.max_pending_images}")
        for name in ("imu_wait_s", "imu_gap_s", "clock_jump_s", "stall_s", "imu_keep_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")


@dataclass
class _Pending:
    timestamp_ns: int
    image: np.ndarray
    arrived: float
    flags: set[str] = field(default_factory=set)


class RobotCore:
    """Policy of one robot's stream to one edge: what is tracked, dropped, sent and shown.

    ``width``, ``height``: the calibrated image size; ``poses``: where the edge's poses and
    the capture times go (shared across edge sessions by the service); ``config``: the
    live-input limits."""

    def __init__(
        self,
        width: int,
        height: int,
        config: LiveInputConfig | None = None,
        poses: PoseTrack | None = None,
        uplink: UplinkBudget | None = None,
    ) -> None:
        self.width, self.height = int(width), int(height)
        self.config = config or LiveInputConfig()
        self.uplink = uplink if uplink is not None else UplinkBudget()
        self.frames_left_out = 0
        self.poses = poses if poses is not None else PoseTrack()
        self.offset_ns = 0  # the edge's camera-IMU offset (t_imu = t_cam + it)
        self.counts: dict[str, int] = dict.fromkeys(FAULTS, 0)
        self.images_in = self.imu_in = self.frames_tracked = self.frames_sent = 0
        self.ended = False
        self._imu: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._imu_last: int | None = None  # newest IMU sample accepted [ns]
        self._imu_last_wall: float | None = None
        self._cut_last: int | None = None  # last IMU sample handed to a frame [ns]
        self._gaps: deque[tuple[int, int]] = deque(maxlen=64)  # IMU holes (a, b) [ns]
        self._pending: deque[_Pending] = deque()
        self._feedback: list[Message] = []
        self._image_last: int | None = None  # newest image accepted [ns]
        self._image_last_wall: float | None = None
        self._stalled = {"image": False, "imu": False}
        self._warned: dict[str, float] = {}
        self._flags: dict[int, frozenset[str]] = {}  # frame time -> flags, until its pose

    # ------------------------------------------------------------------ events
    def handle(self, event: Event, now: float) -> list[Action]:
        """Take one event at ``now``; the actions to do, in order."""
        if isinstance(event, ImuInput):
            self._on_imu(event, now)
        elif isinstance(event, ImageInput):
            self._on_image(event, now)
        elif isinstance(event, EdgeInput):
            return self._on_edge(event.message, now)
        elif isinstance(event, EndOfInput):
            self.ended = True
        elif isinstance(event, FrameDone):
            msg = event.message
            if msg is None:  # fresh before complete: no pose will come for it
                self.frames_left_out += 1
                self.uplink.left(event.left_out)
                flags = self._flags.pop(event.timestamp_ns, None)
                if event.predicted is None:
                    self.poses.forget(event.timestamp_ns)
                    return []
                map_id, T = event.predicted
                pose = self.poses.on_predicted(event.timestamp_ns, map_id, T, now)
                return [PoseOut(dataclasses.replace(pose, flags=flags) if flags else pose)]
            self.frames_sent += 1
            nbytes = len(msg.features) + len(msg.imu)
            self.uplink.on_sent(now, nbytes, msg.keyframe, event.features, len(msg.imu))
            return [Send(msg)]
        elif isinstance(event, LinkLoad):
            self.uplink.on_link(now, event.outbox_bytes, event.acked_bytes)
        return []

    def has_room(self) -> bool:
        """True while a new image would not drop an older one."""
        return len(self._pending) < self.config.max_pending_images

    @property
    def pending_images(self) -> int:
        return len(self._pending)

    @property
    def imu_lead_ns(self) -> int:
        """How far past a frame's time its IMU must reach (the offset when positive)."""
        return max(0, self.offset_ns)

    def next_job(self, now: float) -> Job | None:
        """The next CPU work for the (idle) worker, or None: the oldest image once its IMU has
        come (or it waited ``imu_wait_s``, or the input ended), else queued feedback."""
        if self._pending:
            head = self._pending[0]
            lead = self.imu_lead_ns
            covered = self._imu_last is not None and self._imu_last >= head.timestamp_ns + lead
            waited = now - head.arrived >= self.config.imu_wait_s
            if covered or waited or self.ended:
                self._pending.popleft()
                if not covered and not self.ended:
                    head.flags.add("imu_late")
                    self._fault(
                        "imu_late",
                        now,
                        f"image at {head.timestamp_ns} ns waited "
                        f"{now - head.arrived:.2f} s for its IMU: tracked without it",
                    )
                batch = self._cut(head.timestamp_ns + lead)
                if self._holds_gap(batch):
                    head.flags.add("imu_gap")
                if head.flags:
                    self._flags[head.timestamp_ns] = frozenset(head.flags)
                    while len(self._flags) > 1000:
                        del self._flags[next(iter(self._flags))]
                feedback, self._feedback = tuple(self._feedback), []
                self.frames_tracked += 1
                hold = self.uplink.hold_back(now)
                plan = self.uplink.keyframe_plan()
                return TrackFrame(head.timestamp_ns, head.image, batch, feedback, hold, plan)
        if self._feedback:
            feedback, self._feedback = tuple(self._feedback), []
            return ApplyFeedback(feedback)
        return None

    # ------------------------------------------------------------------ timers
    def timer(self) -> float | None:
        """When :meth:`on_timer` has something to check (monotonic s), or None."""
        times = []
        if self._pending and not self.ended:
            times.append(self._pending[0].arrived + self.config.imu_wait_s)
        if not self.ended and not self._pending:
            for kind, last in (("image", self._image_last_wall), ("imu", self._imu_last_wall)):
                if last is not None and not self._stalled[kind]:
                    times.append(last + self.config.stall_s)
        return min(times) if times else None

    def on_timer(self, now: float) -> None:
        """Warn of a stalled driver (an image late for its IMU is :meth:`next_job`'s)."""
        if self.ended or self._pending:  # waiting for tracking, not for the driver
            return
        for kind, last in (("image", self._image_last_wall), ("imu", self._imu_last_wall)):
            if last is not None and not self._stalled[kind] and now - last >= self.config.stall_s:
                self._stalled[kind] = True
                self.counts[f"{kind}_stall"] += 1
                logger.warning(
                    "no %s for %.1f s: is the driver stalled? (poses stop until it comes back)",
                    "image" if kind == "image" else "IMU sample",
                    now - last,
                )

    # ------------------------------------------------------------------ stats
    def stats(self) -> dict[str, Any]:
        """Counters: input taken, frames tracked and sent, faults per kind, the poses."""
        return {
            "images_in": self.images_in,
            "imu_in": self.imu_in,
            "frames_tracked": self.frames_tracked,
            "frames_sent": self.frames_sent,
            "frames_left_out": self.frames_left_out,
            "uplink": self.uplink.stats(),
            "pending_images": len(self._pending),
            "faults": dict(self.counts),
            "poses": self.poses.summary(),
        }

    # ------------------------------------------------------------------ internals
    def _fault(self, kind: str, now: float, text: str) -> None:
        self.counts[kind] += 1
        last = self._warned.get(kind)
        if last is None or now - last >= self.config.warn_interval_s:
            self._warned[kind] = now
            logger.warning("%s (%s: %d so far)", text, kind, self.counts[kind])

    def _resumed(self, kind: str, now: float, last: float | None) -> None:
        if self._stalled[kind]:
            self._stalled[kind] = False
            gap = now - last if last is not None else float("nan")
            logger.warning("%s again after %.1f s", "images" if kind == "image" else "IMU", gap)

    def _on_imu(self, ev: ImuInput, now: float) -> None:
        ts = np.asarray(ev.timestamps_ns, np.int64).reshape(-1)
        gyro = np.asarray(ev.gyro, np.float64).reshape(-1, 3)
        accel = np.asarray(ev.accel, np.float64).reshape(-1, 3)
        if not len(ts) == len(gyro) == len(accel):
            self._fault(
                "imu_invalid",
                now,
                f"IMU input of {len(ts)} stamps, {len(gyro)} gyro "
                f"and {len(accel)} accel rows: dropped",
            )
            return
        self._resumed("imu", now, self._imu_last_wall)
        self._imu_last_wall = now
        self.imu_in += len(ts)
        keep = np.isfinite(gyro).all(axis=1) & np.isfinite(accel).all(axis=1)
        if not keep.all():
            self._fault("imu_invalid", now, f"{int((~keep).sum())} IMU samples not finite: dropped")
        # in order: each sample after the newest kept one
        last = self._imu_last
        order = np.zeros(len(ts), bool)
        for i in np.flatnonzero(keep):
            t = int(ts[i])
            if last is not None and t <= last:
                self._fault(
                    "imu_out_of_order",
                    now,
                    f"IMU sample at {t} ns not after the last one ({last} ns): dropped",
                )
                continue
            if last is not None and t - last > self.config.imu_gap_s * 1e9:
                self._gaps.append((last, t))
                self._fault(
                    "imu_gap",
                    now,
                    f"IMU gap of {(t - last) * 1e-9:.3f} s (limit "
                    f"{self.config.imu_gap_s:.3f} s) before {t} ns: poses across it are "
                    "flagged imu_gap",
                )
            order[i] = True
            last = t
        if last is None or not order.any():
            return
        self._imu_last = last
        self._imu.append((ts[order], gyro[order], accel[order]))
        if self._cut_last is None:  # before the first frame: keep a bounded pre-roll
            floor = last - int(self.config.imu_keep_s * 1e9)
            if int(self._imu[0][0][0]) < floor:
                stamps, g, a = self._imu_arrays()
                k = stamps >= floor
                self._imu = [(stamps[k], g[k], a[k])]

    def _imu_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if not self._imu:
            return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3))
        if len(self._imu) > 1:
            t, g, a = (np.concatenate(parts) for parts in zip(*self._imu, strict=True))
            self._imu = [(t, g, a)]
        return self._imu[0]

    def _cut(self, until_ns: int) -> ImuBatch:
        """The samples after the last frame's up to and including the first at or after
        ``until_ns`` (none when the last frame's already reached it)."""
        t, g, a = self._imu_arrays()
        if self._cut_last is not None and self._cut_last >= until_ns:
            n = 0
        else:
            n = min(int(np.searchsorted(t, until_ns, side="left")) + 1, len(t))
        batch = ImuBatch(t[:n].copy(), g[:n].copy(), a[:n].copy())
        self._imu = [(t[n:], g[n:], a[n:])] if n < len(t) else []
        if n:
            self._cut_last = int(t[n - 1])
        elif self._cut_last is None:
            self._cut_last = until_ns
        return batch

    def _holds_gap(self, batch: ImuBatch) -> bool:
        if not len(batch.timestamps_ns) or not self._gaps:
            return False
        lo, hi = int(batch.timestamps_ns[0]), int(batch.timestamps_ns[-1])
        hit = any(lo <= b <= hi for _, b in self._gaps)
        while self._gaps and self._gaps[0][1] <= hi:
            self._gaps.popleft()
        return hit

    def _on_image(self, ev: ImageInput, now: float) -> None:
        self.images_in += 1
        t = int(ev.timestamp_ns)
        try:
            image = self._image(ev)
        except ImageError as exc:
            self._fault("image_invalid", now, f"image at {t} ns dropped: {exc}")
            return
        last, jump = self._image_last, int(self.config.clock_jump_s * 1e9)
        if last is not None and t <= last:
            if t < last - jump:
                self._fault(
                    "clock_back",
                    now,
                    f"camera clock went back {(last - t) * 1e-9:.3f} "
                    "s: images are dropped until it passes the last accepted time "
                    "again (after a clock reset, restart the robot)",
                )
            elif t == last:
                self._fault("image_duplicate", now, f"image at {t} ns again: dropped")
            else:
                self._fault(
                    "image_out_of_order",
                    now,
                    f"image at {t} ns before the last one ({last} ns): dropped",
                )
            return
        flags: set[str] = set()
        if last is not None and self._image_last_wall is not None:
            ahead = (t - last) * 1e-9 - (now - self._image_last_wall)
            if ahead > self.config.clock_jump_s:
                flags.add("clock_jump")
                self._fault(
                    "clock_jump",
                    now,
                    f"camera time jumped {(t - last) * 1e-9:.3f} s "
                    f"in {now - self._image_last_wall:.3f} s of wall time: the pose "
                    "after it is flagged clock_jump",
                )
        self._resumed("image", now, self._image_last_wall)
        self._image_last, self._image_last_wall = t, now
        self.poses.captured(t, now)
        self._pending.append(_Pending(t, image, now, flags))
        if len(self._pending) > self.config.max_pending_images:
            old = self._pending.popleft()
            self.poses.forget(old.timestamp_ns)
            self._fault(
                "dropped_backpressure",
                now,
                f"images come faster than tracking: the "
                f"oldest untracked one ({old.timestamp_ns} ns) was dropped",
            )

    def _image(self, ev: ImageInput) -> np.ndarray:
        """The uint8 (H, W) grey image of an input (ImageError if it cannot be one)."""
        if isinstance(ev.image, np.ndarray):
            img = ev.image
            if img.ndim == 3 and img.shape[2] == 1:
                img = img[:, :, 0]
            if img.dtype != np.uint8 or img.ndim != 2:
                raise ImageError(f"{img.dtype} array of shape {img.shape}, not uint8 (H, W)")
        else:
            img = _decode(ev)
        if img.shape != (self.height, self.width):
            raise ImageError(
                f"{img.shape[1]}x{img.shape[0]}, the calibration says {self.width}x{self.height}"
            )
        return np.ascontiguousarray(img)

    def _on_edge(self, msg: Message, now: float) -> list[Action]:
        if isinstance(msg, FramePose):
            pose = self.poses.on_pose(msg, now)
            if pose is None:
                return []
            flags = self._flags.pop(pose.timestamp_ns, None)
            if flags:
                pose = dataclasses.replace(pose, flags=flags)
            return [PoseOut(pose)]
        if isinstance(msg, MapPlacement):  # where the robot's map sits in the global map
            self.poses.on_placement(msg)
            return []
        if isinstance(msg, CameraImuOffset):
            self.offset_ns = int(msg.offset_ns)
        elif not isinstance(msg, InertialFeedback | InertialFeedbackCoded):
            logger.warning("robot ignores %s from the edge", type(msg).__name__)
            return []
        self._feedback.append(msg)
        return []


def _decode(ev: ImageInput) -> np.ndarray:
    """A raw image's uint8 (H, W) grey pixels (ImageError if the encoding is not known or the
    bytes do not fit)."""
    enc, h, w, step = ev.encoding, int(ev.height), int(ev.width), int(ev.step)
    channels = {
        "mono8": 1,
        "8UC1": 1,
        "mono16": 2,
        "16UC1": 2,
        "bgr8": 3,
        "rgb8": 3,
        "bgra8": 4,
        "rgba8": 4,
    }
    if enc not in channels:
        raise ImageError(f"encoding {enc!r} is not one of {ENCODINGS}")
    row = w * channels[enc]
    data = bytes(ev.image) if not isinstance(ev.image, bytes) else ev.image
    if h <= 0 or w <= 0 or step < row or len(data) < step * h:
        raise ImageError(f"{enc} {w}x{h} step {step} does not fit {len(data)} bytes")
    rows = np.frombuffer(data, np.uint8, count=step * h).reshape(h, step)[:, :row]
    if channels[enc] == 1:
        return rows
    if enc in ("mono16", "16UC1"):
        return (np.ascontiguousarray(rows).view("<u2") >> 8).astype(np.uint8)
    px = rows.reshape(h, w, channels[enc])
    code = {
        "bgr8": cv2.COLOR_BGR2GRAY,
        "rgb8": cv2.COLOR_RGB2GRAY,
        "bgra8": cv2.COLOR_BGRA2GRAY,
        "rgba8": cv2.COLOR_RGBA2GRAY,
    }[enc]
    return cv2.cvtColor(np.ascontiguousarray(px), code)

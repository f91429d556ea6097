"""The robot core's runner on an asyncio loop: events in, one worker thread, sends out.

:class:`RobotEngine` owns a :class:`~services.robot.core.RobotCore` (the policy) and a
:class:`~services.robot.app.RobotApp` (the front end and codecs). Events come from the loop
(:meth:`RobotEngine.handle`) or from any thread (:meth:`RobotEngine.submit`, which hops onto
the loop): the core is only ever touched on the loop, the app only on the worker thread (a
single-thread executor), so neither needs a lock. One worker task asks the core for the next
job, runs it on the worker thread, and awaits each resulting send before asking again: a full
outbox towards the edge holds tracking back, and images then queue in the core, which drops
the oldest (stated back-pressure). Poses go to ``on_pose`` on the loop as they arrive. The
core's timer is armed with one ``loop.call_later``.

Both the CLI's folder and bag playback (:mod:`services.robot.server`) and the library API
(:mod:`services.robot.client`) run their robot through this class.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Awaitable, Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from common.protocol.messages import Message
from common.transport import Delivery
from services.robot.app import RobotApp
from services.robot.core import (
    Action,
    ApplyFeedback,
    EdgeInput,
    EndOfInput,
    Event,
    FrameDone,
    Job,
    LinkLoad,
    PoseOut,
    RobotCore,
    Send,
    TrackFrame,
)
from services.robot.poses import ReceivedPose

logger = logging.getLogger(__name__)

SendFn = Callable[[Message], Awaitable[bool]]
"""Queue a message to the edge, waiting while the link is full; False: give up (abort)."""


def run_job(app: RobotApp, job: Job) -> FrameDone | None:
    """Do one job of the core on the worker thread."""
    for msg in job.feedback:
        app.receive(msg)
    if isinstance(job, ApplyFeedback):
        app.apply_pending()
        return None
    app.set_keyframe_plan(job.plan)
    outage = job.hold_back == "outage"  # (keyframes are left out too)
    frame = app.process_if(
        job.timestamp_ns, job.image, job.imu, send=not job.hold_back, send_keyframe=not outage
    )
    predicted = app.predicted_pose(job.timestamp_ns) if frame is None else None
    features = len(app.frame_coder.track_ids) if frame is not None and frame.keyframe else 0
    return FrameDone(frame, job.timestamp_ns, job.hold_back, predicted, features)


def ack_delay_s(camera_rate_hz: float) -> float:
    """How long the robot's link holds an acknowledgement of the edge's messages: one camera
    period (at most 0.2 s), so that it rides on the next frame's header (each carries the
    cumulative ack) rather than costing an ``Ack`` frame of its own."""
    return min(0.2, 1.0 / max(camera_rate_hz, 1e-3))


class RobotEngine:
    """Core + front end + worker thread on the running loop (see the module docstring)."""

    def __init__(
        self,
        core: RobotCore,
        app: RobotApp,
        executor: ThreadPoolExecutor,
        send: SendFn,
        on_pose: Callable[[ReceivedPose], None] | None = None,
        link_load: Callable[[], tuple[int, int]] | None = None,
    ) -> None:
        self.core = core
        self.link_load = link_load  # (bytes unacknowledged, bytes acknowledged so far)
        self.app = app
        self.executor = executor
        self.send = send
        self.on_pose = on_pose
        self.loop = asyncio.get_running_loop()
        self._wake = asyncio.Event()
        self._idle = asyncio.Event()
        self._room = asyncio.Event()
        self._room.set()
        self._closing = False
        self._stopped = False  # a send gave up: nothing more is tracked
        self._timer: asyncio.TimerHandle | None = None
        self._task = self.loop.create_task(self._work(), name="robot-worker")

    # ------------------------------------------------------------------ input
    def submit(self, event: Event) -> None:
        """Hand an event to the core from any thread."""
        self.loop.call_soon_threadsafe(self.handle, event)

    def handle(self, event: Event) -> None:
        """Hand an event to the core (on the loop)."""
        self._do(self.core.handle(event, time.monotonic()))
        self._after()

    async def on_delivery(self, delivery: Delivery) -> None:
        """The transport's handler: the edge's messages go to the core."""
        self.handle(EdgeInput(delivery.message))

    async def room(self) -> None:
        """Until a new image would not drop an older one (a playback that must not drop);
        re-raises the worker's error (e.g. the edge refused the robot)."""
        while not self.core.has_room() and not self._stopped:
            if self._task.done():
                self._task.result()
                return
            self._room.clear()
            room = asyncio.ensure_future(self._room.wait())
            try:
                await asyncio.wait({self._task, room}, return_when=asyncio.FIRST_COMPLETED)
            finally:
                room.cancel()

    async def drain(self) -> None:
        """End of input: until every image taken is tracked and its message sent (or a send
        gave up); re-raises the worker's error."""
        self.handle(EndOfInput())
        while True:
            if self._task.done():
                self._task.result()
                return
            if self._stopped or (self._idle.is_set() and self.core.pending_images == 0):
                return
            self._idle.clear()
            self._wake.set()
            idle = asyncio.ensure_future(self._idle.wait())
            try:
                await asyncio.wait({self._task, idle}, return_when=asyncio.FIRST_COMPLETED)
            finally:
                idle.cancel()

    async def close(self) -> None:
        """Stop the worker (after the job in progress) and the timer."""
        self._closing = True
        self._wake.set()
        if self._timer is not None:
            self._timer.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._task

    def stats(self) -> dict[str, Any]:
        return self.core.stats()

    # ------------------------------------------------------------------ internals
    def _do(self, actions: list[Action]) -> None:
        for action in actions:
            if isinstance(action, PoseOut):
                if self.on_pose is not None:
                    self.on_pose(action.pose)
            else:  # pragma: no cover - inputs never make the core send
                raise AssertionError(f"unexpected action {action!r} outside the worker")

    def _after(self) -> None:
        self._wake.set()
        if self.core.has_room():
            self._room.set()
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        due = self.core.timer()
        if due is not None and not self._closing:
            self._timer = self.loop.call_later(max(0.0, due - time.monotonic()), self._on_timer)

    def _on_timer(self) -> None:
        self._timer = None
        self.core.on_timer(time.monotonic())
        self._after()

    async def _work(self) -> None:
        while not self._closing:
            if self.link_load is not None:
                outbox, acked = self.link_load()
                self.core.handle(LinkLoad(outbox, acked), time.monotonic())
            job = self.core.next_job(time.monotonic())
            self._after()
            if job is None:
                self._idle.set()
                self._wake.clear()
                await self._wake.wait()
                continue
            self._idle.clear()
            done = await self.loop.run_in_executor(self.executor, run_job, self.app, job)
            if done is None:
                continue
            for action in self.core.handle(done, time.monotonic()):
                if isinstance(action, Send) and not await self.send(action.message):
                    self._stopped = True
                    self._room.set()
                    self._idle.set()
                    return
            if isinstance(job, TrackFrame):
                self._room.set()
        self._idle.set()

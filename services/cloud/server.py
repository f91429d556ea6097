"""The cloud network service: edges connect, keyframes flow in, corrections flow back.

:class:`CloudServer` is the asyncio runner of the cloud's sans-I/O
:class:`~services.cloud.core.CloudCore` (the schedule of pose graphs, full BA and MBP is
described there, once) and owns the lifecycle:

- a :class:`common.transport.Server` accepts any number of edges (each serving several
  robots; the connection's agent id is the edge id, ``KeyframeUpdate.agent_id`` the robot);
- every message goes to the core (and its :class:`~services.cloud.app.CloudApp`) on a single
  *worker* thread (decode, place recognition, verification, merging, SQLite commit); every
  call of the core and the app runs there. The transport acknowledges after the handler
  returns, i.e. after the commit: acknowledged = durable. A malformed or inconsistent
  message (any ``RecslamError`` but a storage failure; e.g. about a robot another edge
  serves) is refused once: recorded as delivered without effect, and the edge is told why
  (``RejectedMessageError``: a ``Reject``), so one bad message can neither wedge an edge's
  stream nor come back. A storage failure (disk full, read-only state) is not the
  message's fault: the transport retries it with backoff, holding the edge back;
- the core's one timer (:meth:`CloudCore.next_deadline`) is a task on the event loop, with loop time
  as ``now``; the solves it asks for run in a separate *optimizer* process (gtsam holds the GIL for
  most of a solve, so a thread would starve the event loop: measured in
  ``benchmarks/results/cloud_service.md``; ``ProcessConfig.optimizer_process`` False uses a thread),
  and the corrected poses go to the edges as ``PoseCorrection`` in each robot's own map frame;
- at :meth:`CloudServer.stop`: a solve in flight is waited for and applied (the optimizer
  process would finish it anyway, and the shutdown's own solve would queue behind it), the
  rest of its round is handed back to the core (:meth:`CloudCore.cancel`), then the core's
  shutdown sequence runs and the trajectories are written;
- the dashboard's :class:`~services.cloud.store.map_source.CloudMapSource` is refreshed every
  ``MapViewConfig.publish_every_s``; trajectories (and the ATE report with ground truth) are written
  every ``StoreConfig.output_every_s`` and at :meth:`CloudServer.stop`
  (:mod:`services.cloud.server_outputs`);
- with ``record``, every applied uplink message is appended to a recording
  (:mod:`services.cloud.store.recording`) on the worker, right after it was applied.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import math
import multiprocessing
import os
import time
from collections import deque
from collections.abc import Callable, Iterable
from concurrent.futures import BrokenExecutor, Executor, ProcessPoolExecutor, ThreadPoolExecutor
from pathlib import Path
from ssl import SSLContext
from typing import Any, TypeVar

from common.calibration import CameraCalibration
from common.errors import RecslamError
from common.evaluation.trajectory import Trajectory
from common.links import CodecTimer
from common.protocol import OutboxFullError, SessionConfig
from common.protocol.errors import LocalProtocolError, RejectedMessageError
from common.transport import Delivery, Server, TransportConfig
from common.vocabulary import Vocabulary
from services.cloud.app import CloudApp, PositionStore, open_app
from services.cloud.app_optimization import Correction
from services.cloud.child_process import child_process_init
from services.cloud.core import CloudCore
from services.cloud.core_actions import (
    Action,
    Outcome,
    SendCorrections,
    SolveKind,
    SolveRequest,
    SolveResult,
)
from services.cloud.decode_pool import DecodePool, Predecoded
from services.cloud.load import BusyMeter
from services.cloud.optimization.global_optimization import warm_up
from services.cloud.server_outputs import ServerOutputs
from services.cloud.service_config import CloudServiceConfig
from services.cloud.stats import CloudStats
from services.cloud.store.map_source import CloudMapSource
from services.cloud.store.output import OutputWriter
from services.cloud.store.persistence import PersistenceError
from services.cloud.store.recording import RecordingWriter

log = logging.getLogger(__name__)

T = TypeVar("T")


def _applied(outcomes: Iterable[Outcome], map_id: int, kind: SolveKind) -> bool:
    return not any(o.map_id == map_id and o.kind is kind and not o.applied for o in outcomes)


class CloudServer(ServerOutputs):
    """The cloud service. ``await start(host, port)`` ... ``await stop()``.

    Args:
        session: protocol settings (role "cloud", the cloud's agent id, shared secret).
        state_dir: SQLite state directory (resumed if it holds a previous run).
        camera: the fallback camera, for robots whose edge sent no calibration (each robot's
            own arrives as ``AgentSensors``; None: such robots' keyframes are refused).
        vocabulary: the shared vocabulary (word ids and idf).
        config: service options.
        results_dir: where trajectories/eval go (None: no output files).
        groundtruth: ground-truth source for the ATE report (see common.evaluation.results).
        transport: socket settings.
        record: append every applied uplink message to this recording file (default: none).
        ssl: TLS context of the listening side (None: plain TCP; frames are sealed anyway).
        prior_frame: the ``eval/ate.json`` of the mission whose map this one started in
            (``services.cloud.store.mission``): the ATE is also reported in its frame.
    """

    def __init__(
        self,
        session: SessionConfig,
        state_dir: str | Path,
        camera: CameraCalibration | None,
        vocabulary: Vocabulary,
        config: CloudServiceConfig | None = None,
        results_dir: str | Path | None = None,
        groundtruth: str | Path | None = None,
        transport: TransportConfig | None = None,
        record: str | Path | None = None,
        ssl: SSLContext | None = None,
        prior_frame: str | Path | None = None,
    ) -> None:
        self.session = session
        self.config = config or CloudServiceConfig()
        self.state_dir = Path(state_dir)
        self.camera = camera
        self.vocabulary = vocabulary
        self.map_source = CloudMapSource(
            self.config.map_view.display_spacing_m, self.config.map_view.bandwidth_window_s
        )
        self.output = (
            OutputWriter(Path(results_dir), groundtruth, prior_frame)
            if results_dir is not None
            else None
        )
        self.positions = PositionStore()
        self._worker = ThreadPoolExecutor(1, thread_name_prefix="cloud-worker")
        self._io = ThreadPoolExecutor(1, thread_name_prefix="cloud-io")
        self._optimizer = self._new_optimizer()
        self._decode_pool = DecodePool(self.config.processes.decode_workers, vocabulary)
        self._app: CloudApp | None = None
        self._core: CloudCore | None = None
        self._server = Server(
            session, self._on_message, transport=transport, ssl=ssl, store=self.positions
        )
        self._wake = asyncio.Event()  # the core's deadline moved
        self._armed: float | None = math.nan  # the deadline the timer sleeps on (nan: none yet)
        self._round_lock = asyncio.Lock()  # one round of the core at a time
        self._tasks: list[asyncio.Task[None]] = []
        self._stopping = False  # the timer's round ends after its solve in flight
        self._solving: SolveRequest | None = None  # the solve the optimizer runs now
        self._solves_abandoned = 0  # solves whose result was not waited for
        self._corrections = 0
        self._queued = 0  # messages handed to the worker and not applied yet
        self._queued_max = 0
        self._busy = BusyMeter(self.config.overload.window_s)  # the worker's (its thread only)
        self.timer = CodecTimer()  # wall: wait.worker, wall.* (worker thread), solve.* (loop)
        self.cpu_timer = CodecTimer(clock=time.thread_time)  # handle.* (worker thread)
        self._final_stats: CloudStats | None = None
        self.address: tuple[str, int] | None = None
        self._references: dict[str, Trajectory] = {}  # ground truth per robot name
        self._no_reference: set[str] = set()
        self._gt_published = -1e9
        self._record_path = Path(record) if record is not None else None
        self._recorder: RecordingWriter | None = None

    # ------------------------------------------------------------------ lifecycle
    def _new_optimizer(self) -> Executor:
        if self.config.processes.optimizer_process:
            # spawn: no fork of a threaded process; the child imports only the optimiser.
            return ProcessPoolExecutor(
                1,
                mp_context=multiprocessing.get_context("spawn"),
                initializer=child_process_init,
                initargs=(os.getpid(), self.config.processes.optimizer_nice),
            )
        return ThreadPoolExecutor(1, thread_name_prefix="cloud-optimizer")

    async def _on_worker(self, fn: Callable[..., T], *args: Any) -> T:
        return await asyncio.get_running_loop().run_in_executor(
            self._worker, self._busy_in, fn, *args
        )

    def _busy_in(self, fn: Callable[..., T], *args: Any) -> T:
        """``fn(*args)`` on the worker thread, its wall time counted as busy."""
        t0 = time.monotonic()
        try:
            return fn(*args)
        finally:
            self._busy.add(t0, time.monotonic())

    def _open(self, now: float) -> tuple[CloudApp, CloudCore]:
        app = open_app(self.state_dir, self.camera, self.vocabulary, self.config, self.positions)
        core = CloudCore(app)
        core.resume(now)  # a restart re-sends fresh corrections
        return app, core

    async def start(self, host: str = "127.0.0.1", port: int = 0) -> tuple[str, int]:
        """Load the state directory, then listen; returns the bound address."""
        self._optimizer.submit(warm_up)  # import gtsam in the optimizer now, not at a merge
        now = asyncio.get_running_loop().time()
        app, self._core = await self._on_worker(self._open, now)
        self._app = app
        if self._record_path is not None:
            self._recorder = RecordingWriter(self._record_path)
        n = app.atlas.n_keyframes()
        log.info(
            "cloud state %s: %d keyframes, %d map points, maps %s",
            self.state_dir,
            n,
            app.atlas.n_map_points(),
            app.atlas.maps(),
        )
        self.address = await self._server.start(host, port)
        # the core's timer first: stop waits for it, and cancels the others
        self._tasks = [asyncio.create_task(self._optimize_loop(), name="cloud-optimize")]
        if self.config.map_view.publish_every_s > 0:  # 0: no dashboard reads the map view
            self._tasks.append(asyncio.create_task(self._publish_loop(), name="cloud-publish"))
        if self.output is not None and self.config.store.output_every_s > 0:
            self._tasks.append(asyncio.create_task(self._output_loop(), name="cloud-output"))
        return self.address

    async def stop(self, write_output: bool = True) -> None:
        """Close the edges' connections, write the outputs, close the state directory. A
        solve in flight is waited for and applied first; the rest of its round, and the
        shutdown's full BA and MBP, run after."""
        await self._server.close()
        self._stopping = True
        self._wake.set()
        if self._solving is not None:
            log.info(
                "stop: waiting for the %s of map %d in flight",
                self._solving.kind.value,
                self._solving.map_id,
            )
        if self._tasks:  # the timer's loop (the first task) ends after its solve in flight
            await self._tasks[0]
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await t
        self._tasks = []
        if self._app is not None and self._core is not None:
            loop = asyncio.get_running_loop()
            core = self._core
            async with self._round_lock:  # the rest of a round cut short: reschedule it

                def cancel(now: float) -> list[Action]:
                    core.cancel(now)
                    return []

                await self._on_worker(self._step, "cancel", cancel, (), loop.time())
            await self._round("shutdown", core.shutdown)
            self._final_stats = await self.stats()
            if write_output and self.output is not None:
                await self.write_output(evaluate=True)
            await self._on_worker(self._app.close)
            self._app, self._core = None, None
        if self._recorder is not None:
            await self._on_worker(self._recorder.close)
            self._recorder = None
        self._worker.shutdown(wait=True)
        self._io.shutdown(wait=True)
        self._optimizer.shutdown(wait=True)
        self._decode_pool.shutdown()

    async def __aenter__(self) -> CloudServer:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    # ------------------------------------------------------------------ messages
    async def _on_message(self, d: Delivery) -> None:
        app, core = self._app, self._core
        if app is None or core is None:
            raise LocalProtocolError("cloud is not running")
        clock = asyncio.get_running_loop().time  # read on the worker, when the message is applied
        self._queued += 1
        self._queued_max = max(self._queued_max, self._queued)
        try:
            # (the worker owns the app; a stale codec read here only makes the offer miss)
            done = await self._decode_pool.predecode(d.message, app.sensors.codec)
            deadline = await self._on_worker(
                self._handle, core, d, clock, time.time(), clock(), done
            )
        except PersistenceError:
            raise  # not the message's fault: the transport retries it (with backoff)
        except RecslamError as exc:  # malformed or inconsistent input (UplinkError, AtlasError)
            await self._on_worker(app.skip, d.peer, d.stream_id, d.seq)
            raise RejectedMessageError(f"{type(d.message).__name__}: {exc}") from exc
        finally:
            self._queued -= 1
        if deadline != self._armed:  # the schedule changed: the timer re-arms
            self._wake.set()

    def _handle(
        self,
        core: CloudCore,
        d: Delivery,
        clock: Callable[[], float],
        t_recv: float,
        t_queued: float,
        done: Predecoded | None = None,
    ) -> float | None:
        """Apply one message (worker thread), record it when recording; the core's next
        deadline after it. ``t_queued``: the loop time it was handed to the worker; ``done``:
        its features decoded in the decode pool (:class:`DecodePool`)."""
        now = clock()
        self.timer.add("wait.worker", now - t_queued)
        kind = type(d.message).__name__
        if done is not None:
            core.app.decoders.offer(*done)
        try:
            with self.timer.span(f"wall.{kind}"), self.cpu_timer.span(f"handle.{kind}"):
                core.handle(d.peer, d.message, d.stream_id, d.seq, now)
        finally:
            if done is not None:
                core.app.decoders.forget()
        if self._recorder is not None:
            self._recorder.write(d.peer, d.stream_id, d.seq, d.message, t_recv, now)
        self._measure_load(core, now)  # (up to the message before this one)
        return core.next_deadline()

    def _measure_load(self, core: CloudCore, now: float) -> None:
        """Tell the core how busy the worker was lately (worker thread), recorded when that
        changed whether it is overloaded."""
        busy = self._busy.share(time.monotonic())
        if core.load(busy, now) and self._recorder is not None:
            self._recorder.write_step("load", now, (busy,))

    def _step(
        self, name: str, call: Callable[[float], list[Action]], args: tuple[object, ...], now: float
    ) -> list[Action]:
        """``call(now)`` on the core (worker thread), recorded as the step ``name`` (with
        ``args``) when recording, and the solve it asks for as a ``request`` step."""
        recorder = self._recorder
        if recorder is not None:
            recorder.write_step(name, now, args)
        actions = call(now)
        if recorder is not None:
            for a in actions:
                if isinstance(a, SolveRequest):
                    recorder.write_step("request", now, (a.kind.value, a.map_id))
        return actions

    # ------------------------------------------------------------------ optimisation
    async def _optimize_loop(self) -> None:
        """The core's single timer: sleep until its deadline (or until a message moved it),
        then run the round that is due. While the cloud is overloaded it also wakes every
        tenth of ``OverloadConfig.window_s`` to measure the load again: the load falls while no
        message comes, and an overload measured only on messages would outlast the burst
        that caused it (no quiet full BA after the last message)."""
        core = self._core
        assert core is not None
        loop = asyncio.get_running_loop()
        recheck_s = self.config.overload.window_s / 10

        def schedule() -> tuple[float | None, bool]:
            return core.next_deadline(), core.overloaded

        while not self._stopping:
            self._armed = math.nan  # a message handled meanwhile wakes the loop
            self._wake.clear()
            deadline, overloaded = await self._on_worker(schedule)
            self._armed = deadline
            left = None if deadline is None else deadline - loop.time()
            if left is None or left > 0:
                if overloaded:
                    left = recheck_s if left is None else min(left, recheck_s)
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._wake.wait(), left)
                if overloaded:
                    await self._on_worker(self._measure_load, core, loop.time())
                continue
            await self._round("timer", core.on_timer, interruptible=True)

    async def _round(
        self,
        name: str,
        start: Callable[..., list[Action]],
        *args: Any,
        interruptible: bool = False,
    ) -> list[Outcome]:
        """Start a round of the core (``start(*args, now)`` on the worker, recorded as the step
        ``name``) and run it to its end: solves in the optimizer, corrections to the edges. One
        round at a time. Returns the outcomes of its solves. An ``interruptible`` round (the
        timer's) starts no new solve once the service is stopping: the core still counts it
        as running until :meth:`stop` cancels the rest."""
        core = self._core
        assert core is not None
        loop = asyncio.get_running_loop()
        outcomes: list[Outcome] = []

        def begin(now: float) -> list[Action]:
            return start(*args, now)

        async with self._round_lock:
            pending = deque(await self._on_worker(self._step, name, begin, args, loop.time()))
            while pending:
                action = pending.popleft()
                if isinstance(action, Outcome):
                    outcomes.append(action)
                elif isinstance(action, SendCorrections):
                    self._send(action.corrections)
                elif isinstance(action, SolveRequest):
                    if interruptible and self._stopping:
                        break
                    self._solving = action
                    try:
                        result = await self._solve(action)
                    except asyncio.CancelledError:
                        self._solves_abandoned += 1
                        raise
                    except Exception:
                        log.exception("%s of map %d failed", action.kind.value, action.map_id)
                        more = await self._on_worker(
                            self._step,
                            "failed",
                            functools.partial(core.failed, action),
                            (action.kind.value, action.map_id),
                            loop.time(),
                        )
                    else:
                        more = await self._on_worker(
                            self._step,
                            "solved",
                            functools.partial(core.solved, action, result),
                            (action.kind.value, action.map_id),
                            loop.time(),
                        )
                    finally:
                        self._solving = None
                    pending.extend(more)
        return outcomes

    async def _solve(self, request: SolveRequest) -> SolveResult:
        """Run a pure solver in the optimizer (restarted if its process died)."""
        loop = asyncio.get_running_loop()
        try:
            with self.timer.span(f"solve.{request.kind.name.lower()}"):
                return await loop.run_in_executor(self._optimizer, request.job())
        except BrokenExecutor:
            log.error("optimizer process died on map %d; starting a new one", request.map_id)
            self._optimizer.shutdown(wait=False)
            self._optimizer = self._new_optimizer()
            raise

    def _send(self, corrections: Iterable[Correction]) -> None:
        for c in corrections:
            try:
                peer = self._server.peer(c.edge_id)
                peer.send_nowait(c.message)
                self._corrections += 1
                if c.placement is not None:
                    peer.send_nowait(c.placement)
            except LocalProtocolError:
                log.info(
                    "edge %s not connected; correction of %s dropped (next one follows)",
                    c.edge_id,
                    c.message.agent_id,
                )
            except OutboxFullError:
                log.warning(
                    "edge %s outbox full; correction of %s dropped", c.edge_id, c.message.agent_id
                )

    async def optimize_map(self, map_id: int) -> bool:
        """Optimise one map now (off the event loop), apply, send corrections, run MBP and the
        full BA if due. Returns False if the map was merged meanwhile (it is rescheduled)."""
        core = self._core
        assert core is not None
        outcomes = await self._round("optimize", core.optimize, map_id)
        return _applied(outcomes, map_id, SolveKind.POSE_GRAPH)

    async def full_ba_map(
        self, map_id: int, max_seconds: float | None = None, send: bool = True
    ) -> bool:
        """Full bundle adjustment of one map now (off the event loop), applied like a pose
        graph; corrections go to the edges when ``send``. ``max_seconds`` overrides the
        solver's time budget. Returns False if the map was merged meanwhile (rescheduled)."""
        core = self._core
        assert core is not None

        def start(map_id: int, max_seconds: float | None, send: bool, now: float) -> list[Action]:
            return core.full_ba(map_id, now, max_seconds, send)

        outcomes = await self._round("full_ba", start, map_id, max_seconds, send)
        return _applied(outcomes, map_id, SolveKind.FULL_BA)

    async def flush_optimizations(self) -> None:
        """Optimise every map that is scheduled, now (tests, benchmarks)."""
        core = self._core
        assert core is not None
        await self._round("flush", core.flush)

    async def optimize_all(self) -> None:
        """Optimise every map now (tests, benchmarks)."""
        app = self._app
        assert app is not None
        for m in await self._on_worker(app.atlas.maps):
            await self.optimize_map(m)

    # ------------------------------------------------------------------ counters, state
    async def stats(self) -> CloudStats:
        """Counters now (after :meth:`stop`: as they were when the service stopped)."""
        app, core = self._app, self._core
        if app is None and self._final_stats is not None:
            return self._final_stats
        assert app is not None and core is not None

        clock = asyncio.get_running_loop().time

        def collect() -> CloudStats:
            a = app.atlas
            stages = CodecTimer()
            stages.merge(app.stage_timer)
            stages.merge(self.timer)
            stages.merge(self.cpu_timer)
            return CloudStats(
                app.messages,
                app.rejected,
                core.optimizations,
                self._corrections,
                core.mbp_passes,
                a.n_keyframes(),
                a.n_map_points(),
                tuple(a.maps()),
                len(a.merges()),
                len(a.loops()),
                core.full_bas,
                self._queued,
                self._queued_max,
                app.rebase.summary(),
                {
                    "overloaded": float(core.overloaded),
                    "busy": self._busy.share(time.monotonic()),
                    "overloads": core.overloads,
                    "overloaded_s": core.overloaded_seconds(clock()),
                    "full_bas_deferred": core.full_bas_deferred,
                },
                stages.snapshot(),
                solves_abandoned=self._solves_abandoned,
            )

        return await self._on_worker(collect)

    async def call(self, fn: Callable[[CloudApp], T]) -> T:
        """Run ``fn(app)`` on the worker thread (read the state safely from outside)."""
        app = self._app
        assert app is not None
        return await self._on_worker(fn, app)

    @property
    def solving(self) -> tuple[SolveKind, int] | None:
        """The solve the optimizer runs (or whose result is being applied) now: its kind and
        map, or None."""
        s = self._solving
        return None if s is None else (s.kind, s.map_id)

    @property
    def transport(self) -> Server:
        return self._server

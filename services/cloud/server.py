"""The cloud network service: edges connect, keyframes flow in, corrections flow back.

:class:`CloudServer` runs on an asyncio loop and owns the lifecycle:

- a :class:`common.transport.Server` accepts any number of edges (each serving several
  robots; the connection's agent id is the edge id, ``KeyframeUpdate.agent_id`` the robot);
- every message goes to :class:`~services.cloud.app.CloudApp` on a single *worker* thread
  (decode, place recognition, verification, merging, SQLite commit). The transport
  acknowledges after the handler returns, i.e. after the commit: acknowledged = durable.
  A malformed message (any ``RecslamError`` but a storage failure) makes the handler raise,
  which closes that edge's connection only;
  a message that fails ``max_failures`` times in a row is logged and skipped so that one
  bad message cannot wedge an edge's stream forever;
- global optimisation is debounced: a map is scheduled at once after a loop or merge and
  after every ``optimize_every_keyframes`` new keyframes; ``debounce_s`` later the pose
  graph is built on the worker, solved in a separate *optimizer* process (gtsam holds the
  GIL for most of a solve, so a thread would starve the event loop: measured in
  ``benchmarks/results/cloud_service.md``; ``optimizer_process=False`` uses a thread),
  written back on the worker, and the corrected poses go to the edges as
  ``PoseCorrection`` in each robot's own map frame;
- MBP runs on the worker right after an optimisation when due (it mutates the atlas);
- the full bundle adjustment (:mod:`services.cloud.full_ba`, when
  ``domain.full_ba.enabled``) is built on the worker, solved in the same optimizer process
  and applied like a pose graph (corrections to the edges included): right after a map's
  pose-graph optimisation once it has ``full_ba_every_keyframes`` new keyframes since its
  last one, when no keyframe has arrived and nothing is scheduled for ``full_ba_quiet_s``,
  and at :meth:`CloudServer.stop` (pending pose graphs first, then at most
  ``full_ba_at_shutdown_s`` in all for the changed maps) before the trajectories are written;
- the dashboard's :class:`~services.cloud.map_source.CloudMapSource` is refreshed every
  ``publish_every_s``; trajectories (and the ATE report with ground truth) are written every
  ``output_every_s`` and at :meth:`CloudServer.stop`;
- with ``record``, every applied uplink message is appended to a recording
  (:mod:`services.cloud.recording`) on the worker, right after it was applied.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import multiprocessing
import os
import time
from collections.abc import Callable
from concurrent.futures import BrokenExecutor, Executor, ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from common.calibration import CameraCalibration
from common.errors import RecslamError
from common.evaluation.errors import EvaluationError
from common.evaluation.results import load_groundtruth
from common.evaluation.trajectory import Trajectory
from common.protocol import OutboxFullError, SessionConfig
from common.protocol.errors import LocalProtocolError
from common.transport import Delivery, Server, TransportConfig
from common.vocabulary import Vocabulary
from services.cloud.app import CloudApp, Correction, PositionStore, Reaction
from services.cloud.config import CloudServiceConfig
from services.cloud.full_ba import solve_full_ba
from services.cloud.global_optimization import (
    optimize_pose_graph,
    optimizer_process_init,
    warm_up,
)
from services.cloud.map_fusion import MapFusion
from services.cloud.map_source import CloudMapSource
from services.cloud.output import OutputWriter
from services.cloud.persistence import CloudStore, PersistenceError
from services.cloud.recording import RecordingWriter

log = logging.getLogger(__name__)

T = TypeVar("T")


@dataclass(frozen=True)
class CloudStats:
    """Counters of a running service (plain data)."""

    messages: int
    rejected: int
    optimizations: int
    corrections_sent: int
    mbp_passes: int
    keyframes: int
    map_points: int
    maps: tuple[int, ...]
    merges: int
    loops: int
    full_ba_passes: int = 0


class CloudServer:
    """The cloud service. ``await start(host, port)`` ... ``await stop()``.

    Args:
        session: protocol settings (role "cloud", the cloud's agent id, shared secret).
        state_dir: SQLite state directory (resumed if it holds a previous run).
        camera: the robots' camera (verification projects with it).
        vocabulary: the shared vocabulary (word ids and idf).
        config: service options.
        results_dir: where trajectories/eval go (None: no output files).
        groundtruth: ground-truth source for the ATE report (see common.evaluation.results).
        transport: socket settings.
        max_failures: a message whose handler failed this many times is skipped.
        record: append every applied uplink message to this recording file (default: none).
    """

    def __init__(
        self,
        session: SessionConfig,
        state_dir: str | Path,
        camera: CameraCalibration,
        vocabulary: Vocabulary,
        config: CloudServiceConfig | None = None,
        results_dir: str | Path | None = None,
        groundtruth: str | Path | None = None,
        transport: TransportConfig | None = None,
        max_failures: int = 3,
        record: str | Path | None = None,
    ) -> None:
        self.session = session
        self.config = config or CloudServiceConfig()
        self.state_dir = Path(state_dir)
        self.camera = camera
        self.vocabulary = vocabulary
        self.map_source = CloudMapSource(
            self.config.display_spacing_m, self.config.bandwidth_window_s
        )
        self.output = (
            OutputWriter(Path(results_dir), groundtruth) if results_dir is not None else None
        )
        self.positions = PositionStore()
        self._worker = ThreadPoolExecutor(1, thread_name_prefix="cloud-worker")
        self._io = ThreadPoolExecutor(1, thread_name_prefix="cloud-io")
        self._optimizer = self._new_optimizer()
        self._app: CloudApp | None = None
        self._server = Server(session, self._on_message, transport=transport, store=self.positions)
        self._max_failures = max_failures
        self._failures: dict[tuple[str, bytes, int], int] = {}
        self._dirty: set[int] = set()
        self._since_opt: dict[int, int] = {}
        self._since_full: dict[int, int] = {}  # map -> changes since its last full BA
        self._last_keyframe_t = 0.0  # loop time of the last new keyframe
        self._full_bas = 0
        self._trigger = asyncio.Event()
        self._tasks: list[asyncio.Task[None]] = []
        self._optimizations = 0
        self._corrections = 0
        self._mbp_passes = 0
        self._final_stats: CloudStats | None = None
        self.address: tuple[str, int] | None = None
        self._references: dict[str, Trajectory] = {}  # ground truth per robot name
        self._no_reference: set[str] = set()
        self._gt_published = -1e9
        self._record_path = Path(record) if record is not None else None
        self._recorder: RecordingWriter | None = None

    # ------------------------------------------------------------------ lifecycle
    def _new_optimizer(self) -> Executor:
        if self.config.optimizer_process:
            # spawn: no fork of a threaded process; the child imports only the optimiser.
            return ProcessPoolExecutor(
                1,
                mp_context=multiprocessing.get_context("spawn"),
                initializer=optimizer_process_init,
                initargs=(os.getpid(),),
            )
        return ThreadPoolExecutor(1, thread_name_prefix="cloud-optimizer")

    async def _on_worker(self, fn: Callable[..., T], *args: Any) -> T:
        return await asyncio.get_running_loop().run_in_executor(self._worker, fn, *args)

    def _open(self) -> CloudApp:
        store = CloudStore(self.state_dir)
        atlas = store.load()
        wg = None
        if self.config.word_group_level is not None:
            words = range(self.vocabulary.n_words)
            wg = self.vocabulary.ancestor_at_level(list(words), self.config.word_group_level)
        fusion = MapFusion(self.camera, self.vocabulary.idf, self.config.domain, atlas, wg)
        return CloudApp(fusion, store, self.vocabulary, self.config, self.positions)

    async def start(self, host: str = "127.0.0.1", port: int = 0) -> tuple[str, int]:
        """Load the state directory, then listen; returns the bound address."""
        self._optimizer.submit(warm_up)  # import gtsam in the optimizer now, not at a merge
        self._app = await self._on_worker(self._open)
        if self._record_path is not None:
            self._recorder = RecordingWriter(self._record_path)
        n = self._app.atlas.n_keyframes()
        log.info("cloud state %s: %d keyframes, %d map points, maps %s", self.state_dir, n,
                 self._app.atlas.n_map_points(), self._app.atlas.maps())  # fmt: skip
        self._dirty.update(self._app.atlas.maps())  # a restart re-sends fresh corrections
        if self._dirty:
            self._trigger.set()
        self.address = await self._server.start(host, port)
        self._tasks = [
            asyncio.create_task(self._optimize_loop(), name="cloud-optimize"),
            asyncio.create_task(self._publish_loop(), name="cloud-publish"),
        ]
        if self.output is not None and self.config.output_every_s > 0:
            self._tasks.append(asyncio.create_task(self._output_loop(), name="cloud-output"))
        return self.address

    async def stop(self, write_output: bool = True) -> None:
        """Close the edges' connections, write the outputs, close the state directory."""
        await self._server.close()
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await t
        self._tasks = []
        if self._app is not None:
            await self._full_ba_at_shutdown()
            await self._mbp_at_shutdown()
            self._final_stats = await self.stats()
            if write_output and self.output is not None:
                await self.write_output(evaluate=True)
            await self._on_worker(self._app.close)
            self._app = None
        if self._recorder is not None:
            await self._on_worker(self._recorder.close)
            self._recorder = None
        self._worker.shutdown(wait=True)
        self._io.shutdown(wait=True)
        self._optimizer.shutdown(wait=True)

    async def __aenter__(self) -> CloudServer:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    # ------------------------------------------------------------------ messages
    async def _on_message(self, d: Delivery) -> None:
        app = self._app
        if app is None:
            raise LocalProtocolError("cloud is not running")
        key = (d.peer, d.stream_id, d.seq)
        try:
            reaction = await self._on_worker(self._handle, app, d, time.time())
        except PersistenceError:
            raise  # not the message's fault: no ack, it is redelivered
        except RecslamError as exc:  # malformed or inconsistent input (UplinkError, AtlasError)
            n = self._failures.get(key, 0) + 1
            self._failures[key] = n
            if n >= self._max_failures:
                log.error("edge %s: skipping message %d after %d failures: %s", d.peer, d.seq,
                          n, exc)  # fmt: skip
                self._failures.pop(key, None)
                await self._on_worker(app.skip, d.peer, d.stream_id, d.seq)
                return
            log.warning("edge %s: malformed %s (seq %d): %s; closing its connection", d.peer,
                        type(d.message).__name__, d.seq, exc)  # fmt: skip
            raise
        self._failures.pop(key, None)
        self._react(reaction)

    def _handle(self, app: CloudApp, d: Delivery, t_recv: float) -> Reaction:
        """Apply one message (worker thread), then record it when recording."""
        reaction = app.handle(d.peer, d.message, d.stream_id, d.seq)
        if self._recorder is not None:
            self._recorder.write(d.peer, d.stream_id, d.seq, d.message, t_recv)
        return reaction

    def _react(self, reaction: Reaction) -> None:
        trigger = bool(reaction.urgent_maps)
        self._dirty.update(reaction.urgent_maps)
        for m in reaction.urgent_maps:
            self._since_full[m] = self._since_full.get(m, 0) + 1
        if reaction.new_keyframes:
            self._last_keyframe_t = asyncio.get_running_loop().time()
        for m, n in reaction.new_keyframes.items():
            self._since_full[m] = self._since_full.get(m, 0) + n
            self._since_opt[m] = self._since_opt.get(m, 0) + n
            if self._since_opt[m] >= self.config.optimize_every_keyframes:
                self._dirty.add(m)
                trigger = True
        if trigger:
            self._trigger.set()

    # ------------------------------------------------------------------ optimisation
    async def _optimize_loop(self) -> None:
        while True:
            if not await self._wait_trigger_or_quiet():
                await self._full_ba_changed("quiet")
                continue
            await asyncio.sleep(self.config.debounce_s)
            self._trigger.clear()
            maps, self._dirty = sorted(self._dirty), set()
            for m in maps:
                try:
                    await self.optimize_map(m)
                except asyncio.CancelledError:
                    raise
                except Exception:
                    log.exception("optimisation of map %d failed", m)

    async def optimize_map(self, map_id: int) -> bool:
        """Optimise one map now (off the event loop), apply, send corrections, run MBP if
        due. Returns False if the map changed shape meanwhile (it is rescheduled)."""
        app = self._app
        assert app is not None
        self._since_opt[map_id] = 0
        built = await self._on_worker(app.optimization_problem, map_id)
        if built is None:
            return True
        problem, token = built
        result = await self._solve(map_id, optimize_pose_graph, problem,
                                   self.config.domain.optimization)  # fmt: skip
        corrections = await self._on_worker(app.apply_optimization, map_id, result, token)
        if corrections is None:
            log.info("map %d merged while optimising; rescheduling", map_id)
            self._dirty.add(map_id)
            self._trigger.set()
            return False
        self._optimizations += 1
        self._send(corrections)
        if await self._on_worker(app.prune_due, map_id):
            await self._on_worker(app.prune, map_id)
            self._mbp_passes += 1
        if self._since_full.get(map_id, 0) >= self.config.full_ba_every_keyframes:
            await self.full_ba_map(map_id)
        return True

    async def _solve(self, map_id: int, fn: Callable[..., T], *args: Any) -> T:
        """Run a pure solver in the optimizer (restarted if its process died)."""
        loop = asyncio.get_running_loop()
        try:
            return await loop.run_in_executor(self._optimizer, fn, *args)
        except BrokenExecutor:
            log.error("optimizer process died on map %d; starting a new one", map_id)
            self._optimizer.shutdown(wait=False)
            self._optimizer = self._new_optimizer()
            raise

    async def full_ba_map(
        self, map_id: int, max_seconds: float | None = None, send: bool = True
    ) -> bool:
        """Full bundle adjustment of one map now (off the event loop), applied like a pose
        graph; corrections go to the edges when ``send``. ``max_seconds`` overrides the
        solver's time budget. Returns False if the map was merged meanwhile (rescheduled)."""
        app = self._app
        assert app is not None
        self._since_full[map_id] = 0
        built = await self._on_worker(app.full_ba_problem, map_id)
        if built is None:
            return True
        problem, token = built
        cfg = self.config.domain.full_ba
        if max_seconds is not None:
            cfg = dataclasses.replace(cfg, max_seconds=max_seconds)
        result = await self._solve(map_id, solve_full_ba, problem, cfg,
                                   self.config.domain.optimization)  # fmt: skip
        corrections = await self._on_worker(app.apply_optimization, map_id, result, token)
        if corrections is None:
            log.info("map %d merged during its full BA; rescheduling", map_id)
            self._since_full[map_id] = self._since_full.get(map_id, 0) + 1
            return False
        self._full_bas += 1
        if send:
            self._send(corrections)
        return True

    async def _wait_trigger_or_quiet(self) -> bool:
        """Wait for an optimisation trigger (True), or until the maps have been quiet for
        ``full_ba_quiet_s`` while one changed since its last full BA (False)."""
        quiet = self.config.full_ba_quiet_s
        loop = asyncio.get_running_loop()
        while True:
            pending = any(n > 0 for n in self._since_full.values())
            if not (self.config.domain.full_ba.enabled and quiet > 0 and pending):
                await self._trigger.wait()
                return True
            left = self._last_keyframe_t + quiet - loop.time()
            if left <= 0 and not self._dirty:
                return False
            try:
                await asyncio.wait_for(self._trigger.wait(), max(left, 0.1))
                return True
            except TimeoutError:
                continue

    async def _full_ba_changed(self, why: str, deadline: float | None = None,
                               send: bool = True) -> None:  # fmt: skip
        """Full BA of every map that changed since its last one (errors are logged); with
        ``deadline`` (loop time) the solves share what is left until then."""
        loop = asyncio.get_running_loop()
        for m in sorted(m for m, n in self._since_full.items() if n > 0):
            left = None if deadline is None else deadline - loop.time()
            if left is not None and left <= 0:
                log.info("no time left for the full BA of map %d (%s)", m, why)
                continue
            log.info("full BA of map %d (%s)", m, why)
            try:
                await self.full_ba_map(m, left, send)
            except asyncio.CancelledError:
                raise
            except Exception:
                log.exception("full BA of map %d failed", m)

    async def _full_ba_at_shutdown(self) -> None:
        """Pending pose graphs, then a time-bounded full BA of the changed maps."""
        budget = self.config.full_ba_at_shutdown_s
        if not self.config.domain.full_ba.enabled or budget <= 0:
            return
        deadline = asyncio.get_running_loop().time() + budget
        try:
            await self.flush_optimizations()
        except Exception:
            log.exception("pose-graph optimisation at shutdown failed")
        await self._full_ba_changed("shutdown", deadline, send=False)

    async def _mbp_at_shutdown(self) -> None:
        """MBP over every map once the last optimisation is in (``mbp_at_shutdown``): the
        persisted map is pruned, the trajectories keep every pose (retired keyframes)."""
        app = self._app
        if app is None or not (self.config.mbp_at_shutdown and self.config.domain.mbp.enabled):
            return
        for m in await self._on_worker(app.atlas.maps):
            try:
                await self._on_worker(app.prune, m)
                self._mbp_passes += 1
            except Exception:
                log.exception("MBP of map %d at shutdown failed", m)

    def _send(self, corrections: list[Correction]) -> None:
        for c in corrections:
            try:
                self._server.peer(c.edge_id).send_nowait(c.message)
                self._corrections += 1
            except LocalProtocolError:
                log.info("edge %s not connected; correction of %s dropped (next one follows)",
                         c.edge_id, c.message.agent_id)  # fmt: skip
            except OutboxFullError:
                log.warning("edge %s outbox full; correction of %s dropped", c.edge_id,
                            c.message.agent_id)  # fmt: skip

    async def flush_optimizations(self) -> None:
        """Optimise every map that is scheduled, now (tests, shutdown)."""
        maps, self._dirty = sorted(self._dirty), set()
        for m in maps:
            await self.optimize_map(m)

    async def optimize_all(self) -> None:
        """Optimise every map now (tests, benchmarks)."""
        app = self._app
        assert app is not None
        for m in await self._on_worker(app.atlas.maps):
            await self.optimize_map(m)

    # ------------------------------------------------------------------ dashboard, output
    async def publish(self) -> int:
        """Refresh the dashboard's map view now; returns its version."""
        app = self._app
        assert app is not None
        counters = self._server.counters()
        references = await self._load_references()
        view = await self._on_worker(app.view, counters, references)
        return self.map_source.publish(view)

    async def _load_references(self) -> dict[str, Trajectory] | None:
        """Ground truth of the known robots, every ``gt_every_s`` (None in between)."""
        source = self.output.groundtruth if self.output is not None else None
        loop = asyncio.get_running_loop()
        if source is None or loop.time() - self._gt_published < self.config.gt_every_s:
            return None
        self._gt_published = loop.time()
        app = self._app
        assert app is not None
        agents = await self._on_worker(app.agents)
        known = {n for n, _, _ in agents.values()}
        names = known - set(self._references) - self._no_reference
        single = Path(source).is_file() or (Path(source) / "mav0").is_dir()
        if single and len(known) > 1:  # one sequence's ground truth: whose is it?
            names = set()
        for name in sorted(names):
            try:
                refs, _ = await loop.run_in_executor(
                    self._io, load_groundtruth, [name], source, None
                )
            except EvaluationError as exc:
                log.info("no ground truth for %s: %s", name, exc)
                self._no_reference.add(name)
            else:
                self._references.update(refs)
        return dict(self._references) if self._references else None

    async def _publish_loop(self) -> None:
        while True:
            try:
                await self.publish()
            except asyncio.CancelledError:
                raise
            except Exception:
                log.exception("map view refresh failed")
            await asyncio.sleep(self.config.publish_every_s)

    async def write_output(self, evaluate: bool = True) -> list[Path]:
        """Write trajectories (and the ATE report when ground truth is known)."""
        app, out = self._app, self.output
        if app is None or out is None:
            return []
        trajs, maps = await self._on_worker(app.trajectories)
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(self._io, out.write, trajs, maps, evaluate)

    async def _output_loop(self) -> None:
        while True:
            await asyncio.sleep(self.config.output_every_s)
            try:
                await self.write_output(evaluate=True)
            except asyncio.CancelledError:
                raise
            except Exception:
                log.exception("writing outputs failed")

    async def stats(self) -> CloudStats:
        """Counters now (after :meth:`stop`: as they were when the service stopped)."""
        app = self._app
        if app is None and self._final_stats is not None:
            return self._final_stats
        assert app is not None

        def collect() -> CloudStats:
            a = app.atlas
            return CloudStats(
                app.messages, app.rejected, self._optimizations, self._corrections,
                self._mbp_passes, a.n_keyframes(), a.n_map_points(), tuple(a.maps()),
                len(a.merges()), len(a.loops()), self._full_bas,
            )  # fmt: skip

        return await self._on_worker(collect)

    async def call(self, fn: Callable[[CloudApp], T]) -> T:
        """Run ``fn(app)`` on the worker thread (read the state safely from outside)."""
        app = self._app
        assert app is not None
        return await self._on_worker(fn, app)

    @property
    def transport(self) -> Server:
        return self._server

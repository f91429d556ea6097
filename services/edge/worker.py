"""Where one robot's VIO runs: a worker *process* (default) or a worker *thread*.

The event loop decodes a robot's frames (the codec state must outlive any VIO failure) and
hands each decoded frame as a :class:`WorkItem` to that robot's worker; the worker runs
:class:`VioRunner` (``VioManager`` plus bookkeeping) and returns a :class:`WorkResult`.

- :class:`ProcessWorker`: one spawned process per robot, one pipe. numpy/gtsam hold the GIL
  part of the time, so robots in threads of one process partly serialise; separate processes
  use both cores (measured in ``benchmarks/results/edge_rtf.md``). A process that dies is
  respawned; the robot re-initialises (fresh VIO, new map id). Worker processes start with
  single-threaded BLAS (:data:`SINGLE_THREAD_ENV`, unless the operator set those variables):
  the robots' processes already fill the cores, and OpenBLAS threads waiting for a preempted
  peer spin, which cost ~250 ms CPU for one 165×165 Cholesky instead of 0.2 ms.
- :class:`ThreadWorker`: the same runner on a dedicated thread (no process start, no pickling).

An exception inside the VIO is contained in the runner: it is logged, the VIO is replaced by a
fresh one (new map-id range) and the result says ``failed``; other robots never notice.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import multiprocessing
import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from common.calibration import CameraCalibration, ImuCalibration
from common.errors import RecslamError
from services.edge.vio.manager import VioManager
from services.edge.vio.types import (
    FrameObservation,
    FrameResult,
    MapUpdate,
    VioConfig,
    VioState,
)

logger = logging.getLogger(__name__)

MAP_ID_STRIDE = 1000
"""Map ids of a re-initialised VIO start at ``generation * MAP_ID_STRIDE`` (no reuse)."""
GENERATIONS_PER_RUN = 100
"""An edge's ``run``-th start for a robot (:meth:`JournalStore.next_run`) begins at generation
``run * GENERATIONS_PER_RUN``: the re-run of a restarted edge's maps never takes the map ids
of the run before (whose maps the cloud holds; the re-run is not the same map)."""
VIO_COUNTS = (
    "maps_started",
    "relocalised",
    "frames_lost_kept",
    "frames_bridged",
    "bridged_back",
)
"""The ``VioStats`` counters each :class:`WorkResult` carries (the edge's stats: ``vio``)."""


class EdgeWorkerError(RecslamError):
    """A worker could not run (process died and could not be restarted, bad request)."""


@dataclass(frozen=True, eq=False)
class WorkItem:
    """One decoded frame for the VIO: IMU since the previous frame (``imu_t_ns`` (K,) int64,
    ``gyro``/``accel`` (K, 3) rad/s, m/s²) and the observation. ``corrections`` are pose
    corrections to apply first: (map_id, {keyframe id: (4, 4) T_world_body}). ``new_stream``:
    the robot restarted its stream (its frame 0 again, e.g. its process was restarted): the
    VIO starts a new map (the next generation) with this frame."""

    frame_index: int
    imu_t_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    obs: FrameObservation | None
    corrections: tuple[tuple[int, dict[int, np.ndarray]], ...] = ()
    new_stream: bool = False


@dataclass(frozen=True, eq=False)
class WorkResult:
    """The VIO's answer to one :class:`WorkItem` (map ids already offset by the generation)."""

    frame_index: int
    result: FrameResult | None
    state: VioState | None
    updates: tuple[MapUpdate, ...]
    failed: str = ""  # exception text when the VIO threw (it has been re-initialised)
    generation: int = 0
    frame_s: float = 0.0  # wall time of the whole feed_frame (tracking, mapping, BA) [s]
    track_s: tuple[float, ...] = ()  # the VIO's own per-frame tracking durations [s]
    local_ba_s: tuple[float, ...] = ()  # local BA durations during this frame [s]
    corrections_applied: int = 0
    # (map id, {keyframe id: (4, 4) correction}) applied before this frame: every map point
    # moved with its first observer's (``VioManager.pop_point_moves``)
    point_moves: tuple[tuple[int, dict[int, np.ndarray]], ...] = ()
    live_track_ids: np.ndarray | None = None  # (L,) int64 stream numbers with a map point
    live_p_world: np.ndarray | None = None  # (L, 3) m, their map points
    time_offset_ns: int = 0  # the VIO's camera-IMU offset in use (t_imu = t_cam + offset)
    time_offset_sigma_ms: float = float("nan")  # of its last estimate
    timestamp_ns: int = 0  # the frame's camera time (also when the VIO failed on it)
    # the VIO's running totals (``VioStats``): maps started after a loss, recently lost maps
    # tracked again, frames not tracked while their map was kept
    vio_counts: dict[str, int] | None = None


@dataclass(frozen=True)
class WorkerSpec:
    """Everything a worker needs to build a robot's VIO (picklable)."""

    agent_id: str
    camera: CameraCalibration
    imu: ImuCalibration
    options: VioConfig = field(default_factory=VioConfig)
    generation: int = 0


def _offset_update(u: MapUpdate, base: int) -> MapUpdate:
    if base == 0:
        return u
    return MapUpdate(u.map_id + base, u.vi_initialized, u.keyframes, u.points, u.removed_point_ids)


class VioRunner:
    """One robot's VIO with containment: ``step(item) -> WorkResult`` never raises for VIO
    errors; it re-initialises instead. Map ids are ``generation * MAP_ID_STRIDE + vio map``."""

    def __init__(self, spec: WorkerSpec) -> None:
        self.spec = spec
        self.generation = spec.generation
        self.vio = self._new_vio()

    def _new_vio(self) -> VioManager:
        return VioManager(self.spec.camera, self.spec.imu, self.spec.options, self.spec.agent_id)

    @property
    def base(self) -> int:
        return self.generation * MAP_ID_STRIDE

    def step(self, item: WorkItem) -> WorkResult:
        import time

        if item.new_stream:  # its time starts again: a new map, as after a failure
            self.generation += 1
            self.vio = self._new_vio()
            logger.info(
                "robot %s restarted its stream: a new VIO (generation %d, map ids from %d)",
                self.spec.agent_id,
                self.generation,
                self.base,
            )
        n_ba = len(self.vio.stats.local_ba_s)
        n_track = len(self.vio.stats.track_s)
        applied = 0
        try:
            for map_id, poses in item.corrections:
                if map_id - self.base >= 0:
                    applied += self.vio.apply_pose_corrections(map_id - self.base, poses)
            if len(item.imu_t_ns):
                self.vio.feed_imu(item.imu_t_ns, item.gyro, item.accel)
            if item.obs is None:
                return WorkResult(item.frame_index, None, None, (), generation=self.generation)
            t_ns = item.obs.timestamp_ns
            t0 = time.perf_counter()
            result = self.vio.feed_frame(item.obs)
            frame_s = time.perf_counter() - t0
            state = self.vio.get_state()
            updates = tuple(_offset_update(u, self.base) for u in self.vio.pop_map_updates())
        except Exception as exc:  # contained: this robot re-initialises, nobody else notices
            logger.exception(
                "robot %s: VIO failed at frame %d; re-initialising",
                self.spec.agent_id,
                item.frame_index,
            )
            self.generation += 1
            self.vio = self._new_vio()
            return WorkResult(
                item.frame_index,
                None,
                None,
                (),
                failed=f"{type(exc).__name__}: {exc}",
                generation=self.generation,
                timestamp_ns=item.obs.timestamp_ns if item.obs is not None else 0,
            )
        live_ids, live_p = None, None
        vmap = self.vio.current_map
        if state is not None and vmap is not None:
            ids, pts = [], []
            for t in item.obs.track_ids.tolist():
                mp = vmap.point_of(t)
                if mp is not None:
                    ids.append(t)
                    pts.append(mp.p_world)
            live_ids = np.array(ids, np.int64)
            live_p = np.array(pts, np.float64).reshape(-1, 3)
        base = self.base
        if base and result is not None:
            result = FrameResult(
                result.timestamp_ns,
                result.T_world_body,
                result.status,
                result.map_id + base,
                result.n_inliers,
                result.is_new_keyframe,
                result.reason,
            )
        if base and state is not None:
            state = VioState(
                state.timestamp_ns,
                state.map_id + base,
                state.T_world_body,
                state.v_world,
                state.bias_gyro,
                state.bias_accel,
                state.gravity_body,
            )
        return WorkResult(
            item.frame_index,
            result,
            state,
            updates,
            generation=self.generation,
            frame_s=frame_s,
            track_s=tuple(self.vio.stats.track_s[n_track:]),
            local_ba_s=tuple(self.vio.stats.local_ba_s[n_ba:]),
            corrections_applied=applied,
            point_moves=tuple((m + base, d) for m, d in self.vio.pop_point_moves()),
            live_track_ids=live_ids,
            live_p_world=live_p,
            time_offset_ns=self.vio.time_offset_ns,
            time_offset_sigma_ms=self.vio.stats.time_offset_sigma_ms,
            timestamp_ns=t_ns,
            vio_counts={k: getattr(self.vio.stats, k) for k in VIO_COUNTS},
        )


# ------------------------------------------------------------------------------ workers


class ThreadWorker:
    """Runs a robot's :class:`VioRunner` on its own thread."""

    kind = "thread"

    def __init__(self, spec: WorkerSpec) -> None:
        self.spec = spec
        self._pool = ThreadPoolExecutor(1, thread_name_prefix=f"vio-{spec.agent_id}")
        self._runner: VioRunner | None = None

    def _step(self, item: WorkItem) -> WorkResult:
        if self._runner is None:
            self._runner = VioRunner(self.spec)
        return self._runner.step(item)

    async def step(self, item: WorkItem) -> WorkResult:
        return await asyncio.get_running_loop().run_in_executor(self._pool, self._step, item)

    async def close(self) -> None:
        await asyncio.get_running_loop().run_in_executor(None, self._pool.shutdown, True)


# BLAS/OpenMP thread counts for worker processes (numpy reads them when it is first imported,
# which in a spawned worker is while unpickling its target, so they must be in the environment
# the child inherits).
SINGLE_THREAD_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def _process_main(conn: Connection, spec: WorkerSpec, log_level: int) -> None:
    """Entry point of a worker process: serve ``WorkItem``s from the pipe until EOF/None."""
    logging.basicConfig(
        level=log_level,
        format=f"%(asctime)s vio[{spec.agent_id}] %(levelname)s %(name)s: %(message)s",
    )
    runner = VioRunner(spec)
    try:
        conn.send(("ready", os.getpid()))
    except (BrokenPipeError, ConnectionResetError):  # the edge died while we started
        logger.info("edge process gone before the VIO worker was ready; it exits")
        return
    while True:
        try:
            item = conn.recv()
        except (EOFError, OSError):
            return
        if item is None:
            return
        result = runner.step(item)
        try:
            conn.send(result)
        except (BrokenPipeError, ConnectionResetError):  # the edge process is gone
            logger.info("edge process gone; VIO worker exits")
            return


class ProcessWorker:
    """Runs a robot's :class:`VioRunner` in a spawned process; respawns it if it dies."""

    kind = "process"

    def __init__(self, spec: WorkerSpec) -> None:
        self.spec = spec
        self.generation = spec.generation
        self._ctx = multiprocessing.get_context("spawn")
        self._pool = ThreadPoolExecutor(1, thread_name_prefix=f"vio-pipe-{spec.agent_id}")
        self._proc: Any = None
        self._conn: Connection | None = None
        self._lock = threading.Lock()
        self.restarts = 0

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    def _spawn(self) -> None:
        parent, child = self._ctx.Pipe()
        for name, value in SINGLE_THREAD_ENV.items():
            os.environ.setdefault(name, value)  # inherited by the spawned child
        spec = WorkerSpec(
            self.spec.agent_id, self.spec.camera, self.spec.imu, self.spec.options, self.generation
        )
        proc = self._ctx.Process(
            target=_process_main,
            args=(child, spec, logging.getLogger().getEffectiveLevel()),
            name=f"vio-{self.spec.agent_id}",
            daemon=True,
        )
        proc.start()
        child.close()
        try:
            parent.recv()  # ("ready", pid): imports done
        except (EOFError, OSError) as exc:
            proc.join(1.0)
            raise EdgeWorkerError(f"VIO process of {self.spec.agent_id} did not start") from exc
        self._proc, self._conn = proc, parent

    def _kill(self) -> None:
        if self._conn is not None:
            self._conn.close()
        if self._proc is not None:
            self._proc.kill()
            self._proc.join(2.0)
        self._proc = self._conn = None

    def _roundtrip(self, item: WorkItem) -> WorkResult:
        with self._lock:
            if self._conn is None:
                self._spawn()
            assert self._conn is not None
            try:
                self._conn.send(item)
                out = self._conn.recv()
            except (EOFError, OSError, BrokenPipeError) as exc:
                code = None if self._proc is None else self._proc.exitcode
                logger.error(
                    "robot %s: VIO process died (exit %s: %r) at frame %d; respawning "
                    "with a fresh VIO",
                    self.spec.agent_id,
                    code,
                    exc,
                    item.frame_index,
                )
                self._kill()
                self.generation += 1
                self.restarts += 1
                return WorkResult(
                    item.frame_index,
                    None,
                    None,
                    (),
                    failed=f"VIO process died (exit {code})",
                    generation=self.generation,
                    timestamp_ns=item.obs.timestamp_ns if item.obs is not None else 0,
                )
            self.generation = out.generation
            return out

    async def start(self) -> None:
        await asyncio.get_running_loop().run_in_executor(self._pool, self._start_sync)

    def _start_sync(self) -> None:
        with self._lock:
            if self._conn is None:
                self._spawn()

    async def step(self, item: WorkItem) -> WorkResult:
        return await asyncio.get_running_loop().run_in_executor(self._pool, self._roundtrip, item)

    def _close_sync(self) -> None:
        with self._lock:
            if self._conn is not None:
                with contextlib.suppress(OSError, BrokenPipeError):
                    self._conn.send(None)
            if self._proc is not None:
                self._proc.join(3.0)
            self._kill()

    async def close(self) -> None:
        await asyncio.get_running_loop().run_in_executor(self._pool, self._close_sync)
        self._pool.shutdown(wait=True)


Worker = ThreadWorker | ProcessWorker

WorkerFactory = Callable[[WorkerSpec, str], Worker]
"""Builds a robot's worker from its spec and the kind ("process" or "thread"): :func:`make_worker`
unless a test injects its own (e.g. one that crashes its process at a chosen frame)."""


def make_worker(spec: WorkerSpec, kind: str) -> Worker:
    """A worker of ``kind`` "process" or "thread"."""
    if kind == "process":
        return ProcessWorker(spec)
    if kind == "thread":
        return ThreadWorker(spec)
    raise EdgeWorkerError(f"unknown worker kind {kind!r} (expected 'process' or 'thread')")

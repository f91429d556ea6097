"""The cloud's policy without I/O: when to optimise, bundle-adjust and prune the maps.

:class:`CloudCore` wraps the :class:`~services.cloud.app.CloudApp` (which applies messages and
owns the atlas) and keeps the schedule state. It never touches a socket, a clock, a thread or
a process: time enters as ``now`` (seconds, any monotonic origin), solves leave as
:class:`SolveRequest` actions that the caller runs wherever it likes and hands back with
:meth:`CloudCore.solved` (or :meth:`CloudCore.failed`). The asyncio service
(:mod:`services.cloud.server`) runs the solves in an optimizer process; the Table 3 replay
(:mod:`lab.table3`) solves in-process with ``now`` = each record's receive time. Both drive
this one schedule.

The schedule:

- **Pose graph, debounced.** A map is scheduled ("dirty") at once after a loop or merge on it and
  after every ``OptimizationScheduleConfig.every_keyframes`` new keyframes; at
  :meth:`CloudCore.resume` (a restart) every map is, so fresh corrections go out. The first trigger
  arms a deadline ``debounce_s`` later (:meth:`CloudCore.next_deadline`); triggers before it cost
  nothing more. At the deadline (:meth:`CloudCore.on_timer`) the dirty maps are taken in order and
  each one's pose graph is built, solved and applied; the corrected poses go to the edges
  (:class:`SendCorrections`, each robot's poses in its own map frame).
- **A round at a time.** While a round's solve is out, messages keep being handled; a trigger
  that arrives meanwhile arms its deadline ``debounce_s`` after the round ends.
- **Rest after a round.** A scheduled round (debounced or quiet) starts no sooner than
  ``OptimizationScheduleConfig.rest_factor`` times the last round's duration after its end, so that
  as maps grow the optimisation's share of the time stays bounded and the messages keep theirs
  (rounds on request: :meth:`CloudCore.optimize`, ``full_ba``, ``flush``, ``shutdown`` do not wait).
- **Merged during a solve.** If maps were merged while a solve was out
  (``apply_optimization`` returns None: the result is in a stale frame), a pose graph is
  scheduled again (dirty + trigger); a full BA counts as one more change of its map, picked up
  by the next full-BA occasion.
- **MBP when due** (``CloudApp.prune_due``: ``MbpScheduleConfig.every_keyframes`` new keyframes
  since the map's last pass). With full BA on and ``MbpScheduleConfig.after_full_ba``, the pose
  graph that finds it due is followed by a full BA of the map and the pass runs right after that
  full BA is applied (not after the full BA at shutdown: the shutdown pass follows it anyway); else
  the pass runs right after the pose graph is applied.
- **Full bundle adjustment** (when ``domain.full_ba.enabled``), built, solved and applied like a
  pose graph, corrections included: right after a map's pose graph once it has
  ``FullBAScheduleConfig.every_keyframes`` changes (new keyframes, loops / merges) since its last
  full BA; when no new keyframe has arrived for ``FullBAScheduleConfig.quiet_s`` and nothing is
  scheduled ("quiet": every changed map); and at shutdown.
- **Overload** (:meth:`CloudCore.load`: the runner reports the share of recent wall time its worker
  was busy): from ``OverloadConfig.busy`` until it falls to ``OverloadConfig.clear`` the cloud sheds
  what only refines the map: no full BA is started (a due one waits, and so does the MBP pass that
  waits for it; once the load fell, their maps get a pose graph scheduled and they follow it), no
  quiet full BA, and place recognition verifies only consistent candidates (``CloudApp.shed``), and
  the dashboard's map view is refreshed less often (:meth:`CloudCore.publish_every_s`). Messages,
  pose graphs and corrections go on: the edges' queues stay bounded as long as those alone fit the
  cloud's CPU.
- **Shutdown** (:meth:`CloudCore.shutdown`): with full BA on and
  ``FullBAScheduleConfig.at_shutdown_s`` > 0, the scheduled pose graphs first, then a full BA of
  every changed map, the solves sharing ``FullBAScheduleConfig.at_shutdown_s`` in all (a map with no
  time left is skipped; no corrections are sent); then MBP over every map when
  ``MbpScheduleConfig.at_shutdown`` (the persisted map is the pruned one, the trajectories keep
  every pose through the retired keyframes).

A failure of one map's step (build, solve, apply, MBP) is logged and the round goes on with
the next step, as the service always did. A full BA that began and was not applied (its solve
or apply failed, or :meth:`CloudCore.cancel` abandoned its round) gives its map back the
changes it had taken, so the shutdown's full BA still runs on that map. Call everything from
one thread: the core is as thread-unsafe as the app it drives.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import uuid
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from common.protocol.messages import Message
from services.cloud.app import CloudApp, Reaction
from services.cloud.core_actions import (
    Action,
    CloudCoreError,
    Outcome,
    SendCorrections,
    SolveKind,
    SolveRequest,
    SolveResult,
    solve,
)

log = logging.getLogger(__name__)


# The steps of a round (internal).
@dataclass(frozen=True)
class _PoseGraph:
    map_id: int


@dataclass(frozen=True)
class _FullBA:
    map_id: int
    why: str
    deadline: float | None = None  # the solve gets what is left until then
    send: bool = True


@dataclass(frozen=True)
class _FullBAChanged:
    """Expands, when reached, into a full BA of every map changed since its last one."""

    why: str
    deadline: float | None = None
    send: bool = True


@dataclass(frozen=True)
class _PruneAll:
    pass


_Step = _PoseGraph | _FullBA | _FullBAChanged | _PruneAll


def _describe(step: _Step) -> str:
    if isinstance(step, _PoseGraph):
        return f"optimisation of map {step.map_id}"
    if isinstance(step, _FullBA):
        return f"full BA of map {step.map_id} ({step.why})"
    return "full BA of the changed maps" if isinstance(step, _FullBAChanged) else "MBP"


class CloudCore:
    """The cloud's schedule over one :class:`CloudApp` (module docstring).

    Messages: :meth:`handle`. Timer: :meth:`next_deadline`, :meth:`on_timer`. Solves:
    :meth:`solved` / :meth:`failed`. Rounds on request: :meth:`optimize`, :meth:`full_ba`,
    :meth:`flush`, :meth:`shutdown`; :meth:`cancel` abandons the running one.
    """

    def __init__(self, app: CloudApp) -> None:
        self.app = app
        self.config = app.config
        self.session = uuid.uuid4().hex  # names this core's iSAM2 graphs in the optimiser
        self._dirty: set[int] = set()
        self._since_opt: dict[int, int] = {}  # map -> new keyframes since its last pose graph
        self._since_full: dict[int, int] = {}  # map -> changes since its last full BA
        self._full_owed: dict[int, int] = {}  # map -> changes its outstanding full BA took
        self._last_keyframe_t = -math.inf
        self._triggered = False
        self._trigger_t: float | None = None  # None while triggered in a round: set at its end
        self._busy = False
        self._round_t0 = 0.0  # when the running round started
        # no scheduled round before this (see OptimizationScheduleConfig.rest_factor)
        self._rest_until = -math.inf
        self._steps: deque[_Step] = deque()
        self._outstanding: tuple[SolveRequest, _PoseGraph | _FullBA] | None = None
        self.optimizations = 0  # pose graphs applied
        self.full_bas = 0  # full BAs applied
        self.mbp_passes = 0
        self._overloaded_since: float | None = None  # None: not overloaded
        self.overloads = 0  # times the cloud became overloaded
        self.overloaded_s = 0.0  # time spent overloaded (closed spells)
        self.full_bas_deferred = 0  # due full BAs not started because of the load

    # ------------------------------------------------------------------ state
    @property
    def busy(self) -> bool:
        """A round is running (its solve is out or it is being stepped)."""
        return self._busy

    @property
    def dirty(self) -> frozenset[int]:
        """Maps scheduled for a pose graph."""
        return frozenset(self._dirty)

    def changed_since_full_ba(self, map_id: int) -> int:
        return self._since_full.get(map_id, 0)

    @property
    def overloaded(self) -> bool:
        """Shedding the optional work (module docstring, "Overload")."""
        return self._overloaded_since is not None

    # ------------------------------------------------------------------ load
    def load(self, busy: float, now: float) -> bool:
        """The share of the recent wall time (``OverloadConfig.window_s``) the runner's worker was
        busy; True when this changed :attr:`overloaded` (the runner records it then, so that
        a replay of the recording sheds where the service did)."""
        cfg = self.config
        if self.overloaded:
            if busy > cfg.overload.clear:
                return False
            self.overloaded_s += self._spell_s(now)
            self._overloaded_since = None
            log.info("load %.2f: no longer overloaded; full BA and early candidates resume", busy)
            self._resume_deferred(now)
        else:
            if not cfg.overload.busy or busy < cfg.overload.busy:
                return False
            self._overloaded_since = now
            self.overloads += 1
            log.warning(
                "load %.2f: overloaded; no full BA while running and no early loop candidates "
                "until it falls to %.2f",
                busy,
                cfg.overload.clear,
            )
        self.app.shed(self.overloaded)
        return True

    def _pass_waits_for_full_ba(self, map_id: int) -> bool:
        """An MBP pass is due on the map and runs after its full BA."""
        cfg = self.config
        return cfg.domain.full_ba.enabled and cfg.mbp.after_full_ba and self.app.prune_due(map_id)

    def _full_ba_due(self, map_id: int, pass_waits: bool) -> bool:
        """The map's full BA is due after its pose graph: it changed enough since its last
        one, or an MBP pass waits for it (``pass_waits``)."""
        enough = self._since_full.get(map_id, 0) >= self.config.full_ba.every_keyframes
        return self.config.domain.full_ba.enabled and (enough or pass_waits)

    def _resume_deferred(self, now: float) -> None:
        """The maps whose full BA (or MBP pass) the overload deferred get a pose graph, and
        the full BA follows it (else they would wait for their map's next keyframe)."""
        maps = self.app.atlas.maps()
        due = [m for m in maps if self._full_ba_due(m, self._pass_waits_for_full_ba(m))]
        if due:
            self._dirty.update(due)
            self._trigger(now)

    def publish_every_s(self, last_s: float = 0.0) -> float:
        """How long until the dashboard's map view is refreshed again (0: never), given
        that the last refresh took ``last_s`` seconds of the worker."""
        cfg = self.config
        every = cfg.map_view.publish_every_s
        if every <= 0:
            return every
        every = max(every, cfg.map_view.publish_rest_factor * last_s)
        return max(every, cfg.overload.publish_every_s) if self.overloaded else every

    def status(self, now: float) -> str:
        """The load shedding in words, for the dashboard ('' while not overloaded)."""
        if not self.overloaded:
            return ""
        return (
            f"overloaded for {self._spell_s(now):.0f} s: no full BA while running "
            f"({self.full_bas_deferred} deferred so far), only consistent loop candidates"
        )

    def overloaded_seconds(self, now: float) -> float:
        """Time spent overloaded up to ``now`` (the current spell included)."""
        return self.overloaded_s + self._spell_s(now)

    def _spell_s(self, now: float) -> float:
        """How long the current overload has lasted at ``now`` (0: none)."""
        since = self._overloaded_since
        return 0.0 if since is None else max(0.0, now - since)

    # ------------------------------------------------------------------ messages
    def resume(self, now: float) -> None:
        """Schedule every map the app holds (a restarted cloud re-sends fresh corrections)."""
        self._dirty.update(self.app.atlas.maps())
        if self._dirty:
            self._trigger(now)

    def handle(
        self, edge_id: str, message: Message, stream_id: bytes, seq: int, now: float
    ) -> Reaction:
        """Apply one message (``CloudApp.handle``; its errors propagate, nothing is
        scheduled then) and schedule what it changed."""
        reaction = self.app.handle(edge_id, message, stream_id, seq)
        trigger = bool(reaction.urgent_maps)
        self._dirty.update(reaction.urgent_maps)
        for m in reaction.urgent_maps:
            self._since_full[m] = self._since_full.get(m, 0) + 1
        if reaction.new_keyframes:
            self._last_keyframe_t = now
        for m, n in reaction.new_keyframes.items():
            self._since_full[m] = self._since_full.get(m, 0) + n
            self._since_opt[m] = self._since_opt.get(m, 0) + n
            if self._since_opt[m] >= self.config.schedule.every_keyframes:
                self._dirty.add(m)
                trigger = True
        if trigger:
            self._trigger(now)
        return reaction

    def _trigger(self, now: float) -> None:
        if not self._triggered:
            self._triggered = True
            self._trigger_t = None if self._busy else now

    # ------------------------------------------------------------------ timer
    def _quiet_pending(self) -> bool:
        full = self.config.domain.full_ba.enabled and self.config.full_ba.quiet_s > 0
        if not full or self.overloaded or self._dirty:
            return False
        return any(n > 0 for n in self._since_full.values())

    def next_deadline(self) -> float | None:
        """When :meth:`on_timer` has work: the debounce deadline of a trigger, else the quiet
        full BA's (may be ``-inf``: at once); None while a round runs or nothing is due."""
        if self._busy:
            return None
        if self._triggered:
            assert self._trigger_t is not None
            return max(self._trigger_t + self.config.schedule.debounce_s, self._rest_until)
        if self._quiet_pending():
            return max(self._last_keyframe_t + self.config.full_ba.quiet_s, self._rest_until)
        return None

    def on_timer(self, now: float) -> list[Action]:
        """Start the round that is due at ``now`` (none: ``[]``); returns its first actions."""
        deadline = self.next_deadline()
        if deadline is None or now < deadline:
            return []
        if self._triggered:
            self._triggered, self._trigger_t = False, None
            maps, self._dirty = sorted(self._dirty), set()
            return self._start([_PoseGraph(m) for m in maps], now)
        return self._start([_FullBAChanged("quiet")], now)

    # ------------------------------------------------------------------ rounds on request
    def optimize(self, map_id: int, now: float) -> list[Action]:
        """A pose graph of ``map_id`` now (with MBP and full BA when due, as scheduled)."""
        return self._start([_PoseGraph(map_id)], now)

    def full_ba(
        self, map_id: int, now: float, max_seconds: float | None = None, send: bool = True
    ) -> list[Action]:
        """A full BA of ``map_id`` now; ``max_seconds`` overrides the solver's time budget;
        corrections are sent when ``send``."""
        deadline = None if max_seconds is None else now + max_seconds
        return self._start([_FullBA(map_id, "requested", deadline, send)], now)

    def flush(self, now: float) -> list[Action]:
        """The pose graphs of every scheduled map now, without waiting for the debounce."""
        self._check_idle()
        self._triggered, self._trigger_t = False, None
        maps, self._dirty = sorted(self._dirty), set()
        return self._start([_PoseGraph(m) for m in maps], now)

    def shutdown(self, now: float) -> list[Action]:
        """The shutdown sequence (module docstring); the full BAs share what is left of
        ``FullBAScheduleConfig.at_shutdown_s`` counted from ``now``."""
        self._check_idle()
        cfg = self.config
        steps: list[_Step] = []
        budget = cfg.full_ba.at_shutdown_s
        if cfg.domain.full_ba.enabled and budget > 0:
            self._triggered, self._trigger_t = False, None
            maps, self._dirty = sorted(self._dirty), set()
            steps += [_PoseGraph(m) for m in maps]
            steps.append(_FullBAChanged("shutdown", now + budget, send=False))
        if cfg.mbp.at_shutdown and cfg.domain.mbp.enabled:
            steps.append(_PruneAll())
        return self._start(steps, now)

    def cancel(self, now: float) -> None:
        """Abandon the running round (its solve's result will not come back): the maps whose
        pose graph it had not applied yet are scheduled again, and a full BA it had out is owed
        again (its map's changes count for the next full BA, at the latest the shutdown's)."""
        if not self._busy:
            return
        maps = [s.map_id for s in self._steps if isinstance(s, _PoseGraph)]
        if self._outstanding is not None and isinstance(self._outstanding[1], _PoseGraph):
            maps.append(self._outstanding[1].map_id)
        if self._outstanding is not None and isinstance(self._outstanding[1], _FullBA):
            self._owe_full_ba(self._outstanding[1].map_id)
        self._steps.clear()
        self._outstanding = None
        self._dirty.update(maps)
        if maps:
            self._trigger(now)
        self._end(now)

    # ------------------------------------------------------------------ solves
    def solved(self, request: SolveRequest, result: SolveResult, now: float) -> list[Action]:
        """Apply the result of ``request`` and go on with the round."""
        step = self._take(request)
        m = request.map_id
        try:
            corrections = self.app.apply_optimization(m, result, request.token)
        except Exception:  # as the service always did: log, go on with the next map
            log.exception("applying the %s of map %d failed", request.kind.value, m)
            if isinstance(step, _FullBA):
                self._owe_full_ba(m)
            return self._advance(now)
        self._full_owed.pop(m, None)
        actions: list[Action] = [Outcome(m, request.kind, corrections is not None)]
        if isinstance(step, _PoseGraph):
            if corrections is None:
                log.info("map %d merged while optimising; rescheduling", m)
                self._dirty.add(m)
                self._trigger(now)
                return actions + self._advance(now)
            self.optimizations += 1
            actions.insert(0, SendCorrections(tuple(corrections)))
            waits = self._pass_waits_for_full_ba(m)
            if not waits:
                self._prune_if_due(m)
            due = self._full_ba_due(m, waits)
            if due and self.overloaded:
                self.full_bas_deferred += 1  # (and the pass that waits for it)
                log.info("full BA of map %d deferred: the cloud is overloaded", m)
            elif due:
                self._steps.appendleft(_FullBA(m, "after its pose graph"))
        elif corrections is None:
            log.info("map %d merged during its full BA; rescheduling", m)
            self._since_full[m] = self._since_full.get(m, 0) + 1
        else:
            self.full_bas += 1
            if step.send:
                actions.insert(0, SendCorrections(tuple(corrections)))
            if self.config.mbp.after_full_ba and step.send:  # not at shutdown
                self._prune_if_due(m)
        return actions + self._advance(now)

    def failed(self, request: SolveRequest, now: float) -> list[Action]:
        """The solve of ``request`` raised (the caller logged it): go on with the round."""
        if isinstance(self._take(request), _FullBA):
            self._owe_full_ba(request.map_id)
        return self._advance(now)

    def _owe_full_ba(self, map_id: int) -> None:
        """A full BA that began was not applied (cancelled, or its solve or apply failed):
        its map keeps the changes it had, so the next occasion (at the latest the shutdown's
        full BA of every changed map) runs it."""
        owed = self._full_owed.pop(map_id, 0)
        self._since_full[map_id] = self._since_full.get(map_id, 0) + owed

    def _take(self, request: SolveRequest) -> _PoseGraph | _FullBA:
        if self._outstanding is None or self._outstanding[0] is not request:
            raise CloudCoreError(f"no such solve out: {request.kind.value} of map {request.map_id}")
        step = self._outstanding[1]
        self._outstanding = None
        return step

    # ------------------------------------------------------------------ stepping
    def _check_idle(self) -> None:
        if self._busy:
            raise CloudCoreError("a round is already running")

    def _start(self, steps: Iterable[_Step], now: float) -> list[Action]:
        self._check_idle()
        self._busy = True
        self._round_t0 = now
        self._steps = deque(steps)
        return self._advance(now)

    def _advance(self, now: float) -> list[Action]:
        """Run the round's next steps up to the next solve (or the round's end)."""
        while self._steps:
            step = self._steps.popleft()
            try:
                request = self._begin(step, now)
            except Exception:  # as the service always did: log, go on with the next map
                log.exception("%s failed", _describe(step))
                continue
            if request is not None:
                assert isinstance(step, _PoseGraph | _FullBA)
                self._outstanding = (request, step)
                return [request]
        self._end(now)
        return []

    def _end(self, now: float) -> None:
        self._busy = False
        rest = self.config.schedule.rest_factor * max(0.0, now - self._round_t0)
        self._rest_until = now + rest if rest > 0 else -math.inf
        if self._triggered and self._trigger_t is None:
            self._trigger_t = now  # triggered during the round: debounce from its end

    def _begin(self, step: _Step, now: float) -> SolveRequest | None:
        """Do one step; a solve to run, or None (nothing to solve, or done in place)."""
        opt = self.config.domain.optimization
        if isinstance(step, _PoseGraph):
            self._since_opt[step.map_id] = 0
            built = self.app.optimization_problem(step.map_id)
            if built is None:
                return None
            return SolveRequest(step.map_id, SolveKind.POSE_GRAPH, built[0], built[1], opt)
        if isinstance(step, _FullBA):
            m = step.map_id
            left = None if step.deadline is None else step.deadline - now
            if left is not None and left <= 0:
                log.info("no time left for the full BA of map %d (%s)", m, step.why)
                return None
            log.info("full BA of map %d (%s)", m, step.why)
            owed, self._since_full[m] = self._since_full.get(m, 0), 0
            full = self.app.full_ba_problem(m)
            if full is None:
                return None
            self._full_owed[m] = owed
            cfg = self.config.domain.full_ba
            if left is not None:
                cfg = dataclasses.replace(cfg, max_seconds=left)
            return SolveRequest(m, SolveKind.FULL_BA, full[0], full[1], opt, cfg, self.session)
        if isinstance(step, _FullBAChanged):
            maps = sorted(m for m, n in self._since_full.items() if n > 0)
            steps = [_FullBA(m, step.why, step.deadline, step.send) for m in maps]
            self._steps.extendleft(reversed(steps))
            return None
        for m in self.app.atlas.maps():  # _PruneAll
            try:
                self.app.prune(m, final=True)
                self.mbp_passes += 1
            except Exception:  # as the service always did: log, go on with the next map
                log.exception("MBP of map %d at shutdown failed", m)
        return None

    def _prune_if_due(self, map_id: int) -> None:
        try:
            if self.app.prune_due(map_id):
                self.app.prune(map_id)
                self.mbp_passes += 1
        except Exception:  # as the service always did: log, go on
            log.exception("MBP of map %d failed", map_id)


def run_inline(
    core: CloudCore,
    actions: Iterable[Action],
    now: float,
    solve_fn: Callable[[SolveRequest], SolveResult] = solve,
) -> list[SendCorrections | Outcome]:
    """Drive a round to its end synchronously: every solve in this thread with ``solve_fn``
    at the same ``now`` (solves take no time). Returns the other actions, in order."""
    pending = deque(actions)
    out: list[SendCorrections | Outcome] = []
    while pending:
        a = pending.popleft()
        if isinstance(a, SolveRequest):
            pending.extend(core.solved(a, solve_fn(a), now))
        else:
            out.append(a)
    return out

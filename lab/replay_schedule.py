"""The cloud service's schedule on a replay's clock (:func:`lab.table3.replay`).

Two ways to drive the service's own :class:`~services.cloud.core.CloudCore` synchronously, its
solves run in this process by a given ``solve_fn``: :class:`SolveClock` (``modelled``: the
core's timer on the records' receive times, each solve taking a chosen share of its wall time)
and :class:`RecordedSteps` (``recorded``: the core calls the service recorded, made again in
order; :class:`ReplayDivergedError` when this configuration schedules otherwise).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterable
from typing import cast

from common.errors import RecslamError
from services.cloud.core import CloudCore
from services.cloud.core_actions import Action, SolveRequest, SolveResult
from services.cloud.store.recording import Step

log = logging.getLogger(__name__)


def _solve_logged(
    solve_fn: Callable[[SolveRequest], SolveResult], request: SolveRequest
) -> SolveResult | None:
    """``solve_fn(request)``, or None if it raised (logged, as the service does: the round
    goes on without it)."""
    try:
        return solve_fn(request)
    except Exception:
        log.exception("%s of map %d failed", request.kind.value, request.map_id)
        return None


def _hand_back(
    core: CloudCore, request: SolveRequest, result: SolveResult | None, now: float
) -> list[Action]:
    """The solve's result to the core (``failed`` when there is none); its next actions."""
    if result is None:
        return core.failed(request, now)
    return core.solved(request, result, now)


class SolveClock:
    """The core's timer and its solves on the replay's clock (records' receive times): a
    round due at a deadline starts at the deadline; a solve requested at ``t`` is solved here
    at once and its result handed back at ``t + latency_scale * (its wall time)``, after the
    records received before then (one round at a time, as in the service)."""

    def __init__(
        self,
        core: CloudCore,
        solve_fn: Callable[[SolveRequest], SolveResult],
        latency_scale: float,
    ) -> None:
        self.core = core
        self.solve_fn = solve_fn
        self.scale = latency_scale
        self.t = -math.inf  # the clock: the time of the newest event
        self._out: tuple[SolveRequest, SolveResult | None, float] | None = None

    def _take(self, actions: Iterable[Action], t: float) -> None:
        """The actions of a round step at ``t``: a solve goes out (anything else, the
        corrections and outcomes, has no effect on a replay)."""
        for a in actions:
            if not isinstance(a, SolveRequest):
                continue
            t0 = time.perf_counter()
            result = _solve_logged(self.solve_fn, a)
            self._out = (a, result, t + self.scale * (time.perf_counter() - t0))

    def _next(self, until: float) -> bool:
        """Run the next event due by ``until``; False when none is."""
        if self._out is not None:
            request, result, ready = self._out
            if ready > until:
                return False
            self._out = None
            self.t = max(self.t, ready)
            self._take(_hand_back(self.core, request, result, self.t), self.t)
            return True
        deadline = self.core.next_deadline()
        if deadline is None or deadline > until:
            return False
        self.t = max(self.t, deadline)
        self._take(self.core.on_timer(self.t), self.t)
        return True

    def advance(self, until: float) -> None:
        """Every event due by ``until``; the clock then reads ``until``."""
        while self._next(until):
            pass
        self.t = max(self.t, until)

    def finish(self) -> float:
        """The round in progress to its end (later solves' results wait for none); returns
        the clock."""
        while self.core.busy:
            if self._out is None:
                raise RecslamError("the cloud core is busy without a solve out")
            self._next(math.inf)
        return self.t

    def run(self, start: Callable[[float], list[Action]], now: float) -> float:
        """A round started on request (``start(now)``, e.g. ``core.flush``) to its end."""
        self.t = max(self.t, now)
        self._take(start(self.t), self.t)
        return self.finish()


class ReplayDivergedError(RecslamError):
    """The recorded schedule does not fit this replay (its configuration schedules otherwise)."""


class RecordedSteps:
    """The service's recorded core calls, made again in order: each solve the core asks for
    is solved here at once and handed back where the service handed its result back."""

    def __init__(self, core: CloudCore, solve_fn: Callable[[SolveRequest], SolveResult]) -> None:
        self.core = core
        self.solve_fn = solve_fn
        self.t = -math.inf
        self.shut_down = False
        self._out: tuple[SolveRequest, SolveResult | None] | None = None

    def _take(self, actions: Iterable[Action]) -> None:
        for a in actions:
            if isinstance(a, SolveRequest):
                self._out = (a, _solve_logged(self.solve_fn, a))

    def _diverged(self, step: Step, why: str) -> ReplayDivergedError:
        return ReplayDivergedError(
            f"recorded step {step.name} {list(step.args)} at offset {step.offset}: {why}; "
            "this configuration schedules otherwise than the recorded service (replay with "
            "schedule='modelled')"
        )

    def step(self, step: Step) -> None:
        core, now, args = self.core, step.now, step.args
        self.t = max(self.t, now)
        if step.name in ("request", "solved", "failed"):
            out = self._out
            if out is None or (out[0].kind.value, out[0].map_id) != tuple(args):
                got = None if out is None else (out[0].kind.value, out[0].map_id)
                raise self._diverged(step, f"the core has {got} out")
            if step.name == "request":
                return
            self._out = None
            request, result = out
            if step.name == "failed" and result is not None:
                log.warning("%s of map %d failed live, not here", *args)
                result = None
            self._take(_hand_back(core, request, result, now))
            return
        if step.name == "cancel":  # the live service abandoned its solve: so does the replay
            self._out = None
            core.cancel(now)
            return
        if step.name == "load":  # the service's load changed its shedding (also mid-solve)
            if not core.load(float(cast(float, args[0])), now):
                raise self._diverged(step, "it does not change this core's overload state")
            return
        if self._out is not None:
            raise self._diverged(step, "a solve is still out")
        if step.name == "timer":
            if core.next_deadline() is None:
                raise self._diverged(step, "no round is due")
            self._take(core.on_timer(now))
        elif step.name == "optimize":
            self._take(core.optimize(cast(int, args[0]), now))
        elif step.name == "full_ba":
            m, max_s, send = args
            self._take(core.full_ba(cast(int, m), now, cast(float | None, max_s), bool(send)))
        elif step.name == "flush":
            self._take(core.flush(now))
        elif step.name == "shutdown":
            self.shut_down = True
            self._take(core.shutdown(now))

    def finish(self) -> None:
        """A round the recording ends in (a service killed mid-solve) solved to its end."""
        while self._out is not None:
            request, result = self._out
            self._out = None
            self._take(_hand_back(self.core, request, result, self.t))

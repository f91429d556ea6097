"""What the cloud's core hands out and takes back (plain data, no I/O): solve requests and
how to run them, corrections to send, outcomes, and the core's error.

A :class:`SolveRequest` is a built optimisation (:mod:`services.cloud.core` decides when);
:meth:`SolveRequest.job` is its pure solve, picklable for the service's optimizer process;
its :data:`SolveResult` goes back to :meth:`~services.cloud.core.CloudCore.solved`.
"""

from __future__ import annotations

import enum
import functools
from collections.abc import Callable
from dataclasses import dataclass

from common.errors import RecslamError
from services.cloud.app_optimization import Correction
from services.cloud.config import FullBAConfig, GlobalOptimizationConfig
from services.cloud.optimization.full_ba import FullBAProblem, FullBAResult, solve_full_ba
from services.cloud.optimization.global_optimization import (
    PoseGraphProblem,
    PoseGraphResult,
    optimize_pose_graph,
)
from services.cloud.optimization.incremental_ba import solve_full_ba_incremental

SolveResult = PoseGraphResult | FullBAResult


class CloudCoreError(RecslamError):
    """Local misuse of the core (a round started while one runs, an unknown request)."""


class SolveKind(enum.Enum):
    POSE_GRAPH = "pose graph"
    FULL_BA = "full BA"


@dataclass(frozen=True, eq=False)
class SolveRequest:
    """A built optimisation to solve: the map, the kind, the plain problem, the atlas' merge
    state when it was built (``token``, handed back to ``apply_optimization``), the
    solver's options (``full_ba`` with its time budget, for a full BA) and the core's
    ``session`` (whose iSAM2 graphs an incremental full BA updates)."""

    map_id: int
    kind: SolveKind
    problem: PoseGraphProblem | FullBAProblem
    token: int
    optimization: GlobalOptimizationConfig
    full_ba: FullBAConfig | None = None
    session: str = ""

    def job(self) -> Callable[[], SolveResult]:
        """The pure solve as a picklable zero-argument callable (a process pool's child
        imports only the solver's module to run it)."""
        if isinstance(self.problem, PoseGraphProblem):
            return functools.partial(optimize_pose_graph, self.problem, self.optimization)
        if self.full_ba is None:
            raise CloudCoreError(f"map {self.map_id}: a full BA request without its options")
        if self.full_ba.incremental:
            return functools.partial(
                solve_full_ba_incremental,
                self.problem,
                self.full_ba,
                self.optimization,
                self.session,
                self.map_id,
            )
        return functools.partial(solve_full_ba, self.problem, self.full_ba, self.optimization)


def solve(request: SolveRequest) -> SolveResult:
    """Solve ``request`` in this thread."""
    return request.job()()


@dataclass(frozen=True)
class SendCorrections:
    """Send these pose corrections to the edges."""

    corrections: tuple[Correction, ...]


@dataclass(frozen=True)
class Outcome:
    """A solve was handed back: ``applied``, or not (maps merged meanwhile: rescheduled)."""

    map_id: int
    kind: SolveKind
    applied: bool


Action = SolveRequest | SendCorrections | Outcome

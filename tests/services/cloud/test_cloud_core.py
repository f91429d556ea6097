"""The cloud's sans-I/O core on a real CloudApp, without asyncio: ``now`` is made up, every
solve runs in this thread when the test hands it back."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from common.vocabulary import Vocabulary
from services.cloud.app import CloudApp, open_app
from services.cloud.config import CloudConfig, FullBAConfig, MbpConfig
from services.cloud.core import CloudCore, run_inline
from services.cloud.core_actions import (
    CloudCoreError,
    Outcome,
    SendCorrections,
    SolveKind,
    SolveRequest,
    solve,
)
from services.cloud.service_config import (
    CloudServiceConfig,
    FullBAScheduleConfig,
    MbpScheduleConfig,
    OptimizationScheduleConfig,
    OverloadConfig,
)
from sim.cloud import (
    circle_poses,
    default_camera,
    encode_session,
    make_session,
    make_world,
    yaw_T,
)


@pytest.fixture(scope="module")
def vocab() -> Vocabulary:
    return Vocabulary.load()


@pytest.fixture(scope="module")
def steps(vocab) -> dict[str, list[list]]:
    """Per robot, per keyframe: the messages an edge sends for it (the keyframe, then the map
    points it observed first). r1's map is offset by a yaw + translation and overlaps r0's:
    the cloud merges them."""
    world = make_world(51)
    cam = default_camera()
    sessions = {
        "r0": make_session(world, cam, 0, circle_poses(24, turns=1.0), np.eye(4), seed=1),
        "r1": make_session(
            world,
            cam,
            1,
            circle_poses(12, turns=0.5, phase=2.0),
            yaw_T(np.radians(-60.0), np.array([-1.5, 0.5, 0.0])),
            seed=2,
            t0=50.0,
        ),
    }
    return {name: encode_session(kfs, mps, name, vocab, 7) for name, (kfs, mps) in sessions.items()}


def _config(
    full_ba: bool = False,
    mbp: bool = False,
    every: int = 1000,
    rest_factor: float = 0.0,
    full_ba_schedule: FullBAScheduleConfig | None = None,
    mbp_schedule: MbpScheduleConfig | None = None,
    overload: OverloadConfig | None = None,
) -> CloudServiceConfig:
    """Full BA and MBP on or off, a pose graph every ``every`` new keyframes (1000: on loops
    and merges only) with no rest after a round, the other groups the service's unless given."""
    domain = CloudConfig(
        full_ba=FullBAConfig(enabled=full_ba, max_iterations=3), mbp=MbpConfig(enabled=mbp)
    )
    return CloudServiceConfig(
        domain=domain,
        schedule=OptimizationScheduleConfig(
            every_keyframes=every, debounce_s=0.5, rest_factor=rest_factor
        ),
        full_ba=full_ba_schedule or FullBAScheduleConfig(),
        mbp=mbp_schedule or MbpScheduleConfig(),
        overload=overload or OverloadConfig(),
    )


class Feed:
    """A core over a fresh in-memory app (no folder, as h11's tests drive its state
    machine), fed one keyframe (with its map points) at a time."""

    def __init__(self, vocab, steps, config: CloudServiceConfig) -> None:
        self.app: CloudApp = open_app(None, default_camera(), vocab, config)
        self.core = CloudCore(self.app)
        self.steps = {name: iter(s) for name, s in steps.items()}
        self.seq = 0

    def keyframe(self, robot: str, now: float) -> bool:
        """The next keyframe of ``robot`` at ``now``; whether maps were merged."""
        merged = False
        for msg in next(self.steps[robot]):
            self.seq += 1
            merged |= self.core.handle("edge", msg, b"stream", self.seq, now).merged
        return merged

    def close(self) -> None:
        self.app.close()


@pytest.fixture
def feed(vocab, steps):
    made: list[Feed] = []

    def make(config: CloudServiceConfig) -> Feed:
        made.append(Feed(vocab, steps, config))
        return made[-1]

    yield make
    for f in made:
        f.close()


def _requests(actions) -> list[SolveRequest]:
    return [a for a in actions if isinstance(a, SolveRequest)]


@pytest.mark.slow
def test_a_keyframe_burst_costs_one_pose_graph_debounce_s_after_the_trigger(feed):
    f = feed(_config(every=3))
    core = f.core
    f.keyframe("r0", 0.0)
    f.keyframe("r0", 0.1)
    assert core.next_deadline() is None and core.on_timer(10.0) == []  # 2 < 3: nothing due
    f.keyframe("r0", 0.2)  # the 3rd new keyframe triggers
    assert core.dirty == {0} and core.next_deadline() == pytest.approx(0.7)
    for i in range(3):  # more keyframes before the deadline do not move it
        f.keyframe("r0", 0.3 + 0.1 * i)
    assert core.next_deadline() == pytest.approx(0.7)
    assert core.on_timer(0.69) == []
    [req] = core.on_timer(0.7)
    assert (req.map_id, req.kind) == (0, SolveKind.POSE_GRAPH) and core.busy
    assert core.next_deadline() is None  # one round at a time
    actions = core.solved(req, solve(req), 0.8)
    sends = [a for a in actions if isinstance(a, SendCorrections)]
    assert len(sends) == 1 and [c.edge_id for c in sends[0].corrections] == ["edge"]
    assert actions[-1] == Outcome(0, SolveKind.POSE_GRAPH, True)
    assert core.optimizations == 1 and not core.busy and core.dirty == frozenset()
    assert core.next_deadline() is None
    # The count restarted at the optimisation: 2 more keyframes do not trigger, the 3rd does.
    f.keyframe("r0", 1.0)
    f.keyframe("r0", 1.1)
    assert core.next_deadline() is None
    f.keyframe("r0", 1.2)
    assert core.next_deadline() == pytest.approx(1.7)


def test_a_trigger_during_a_solve_is_debounced_from_the_end_of_the_round(feed):
    f = feed(_config(every=2))
    core = f.core
    f.keyframe("r0", 0.0)
    f.keyframe("r0", 0.1)
    [req] = core.on_timer(0.6)
    f.keyframe("r0", 0.7)  # messages go on while the solve is out ...
    f.keyframe("r0", 0.8)  # ... and this one triggers again
    assert core.next_deadline() is None and core.dirty == {0}
    core.solved(req, solve(req), 2.0)
    assert core.next_deadline() == pytest.approx(2.5)
    with pytest.raises(CloudCoreError):
        core.solved(req, solve(req), 2.0)  # handed back twice


def test_after_a_long_round_the_next_rests_rest_factor_times_as_long(feed):
    """A round that took 4 s (a big map on a busy core) is followed by 2 s without a
    scheduled one (factor 0.5), whatever the debounce; a short round by the debounce."""
    f = feed(_config(every=2, rest_factor=0.5))
    core = f.core
    f.keyframe("r0", 0.0)
    f.keyframe("r0", 0.1)
    [req] = core.on_timer(0.6)
    f.keyframe("r0", 1.0)
    f.keyframe("r0", 1.1)  # triggers during the round
    core.solved(req, solve(req), 4.6)  # the round took 4 s
    assert core.next_deadline() == pytest.approx(6.6)  # 4.6 + 0.5 * 4, not 4.6 + 0.5
    assert core.on_timer(6.5) == []
    [req] = core.on_timer(6.6)
    f.keyframe("r0", 6.7)
    f.keyframe("r0", 6.8)
    core.solved(req, solve(req), 6.8)  # 0.2 s: the debounce rules
    assert core.next_deadline() == pytest.approx(7.3)
    assert core.optimize(0, 6.9)  # on request: at once


@pytest.mark.slow
def test_a_merge_during_a_solve_reschedules_the_map(feed):
    f = feed(_config())
    core = f.core
    for i in range(24):
        f.keyframe("r0", 0.1 * i)
    run_inline(core, core.flush(2.5), 2.5)  # r0's loop closure: nothing scheduled after it
    assert core.next_deadline() is None
    # r1's own map (1) is optimised before each of its keyframes; one of them merges it into
    # r0's map (0) while that solve is out.
    req, merged, now = None, False, 3.0
    for _ in range(12):
        now += 0.1
        started = core.optimize(1, now) if 1 in f.app.atlas.maps() else []
        req = started[0] if started else None  # none while map 1 has a single keyframe
        merged = f.keyframe("r1", now)
        if merged:
            break
        if req is not None:
            run_inline(core, core.solved(req, solve(req), now), now)
    assert merged and req is not None and req.map_id == 1 and f.app.atlas.maps() == [0]
    with pytest.raises(CloudCoreError):
        core.flush(now)  # a round is already running
    assert core.dirty == {0}  # the merge scheduled the merged map
    n_opt = core.optimizations
    actions = core.solved(req, solve(req), now + 2.0)
    # The result is in a stale frame: nothing applied or sent, map 1 is scheduled again.
    assert actions == [Outcome(1, SolveKind.POSE_GRAPH, False)]
    assert core.optimizations == n_opt and core.dirty == {0, 1}
    assert core.next_deadline() == pytest.approx(now + 2.5)  # debounced from the round's end
    out = run_inline(core, core.on_timer(now + 2.5), now + 2.5)
    assert [o for o in out if isinstance(o, Outcome)] == [Outcome(0, SolveKind.POSE_GRAPH, True)]
    sent = {
        c.message.agent_id for a in out if isinstance(a, SendCorrections) for c in a.corrections
    }
    assert sent == {"r0", "r1"} and core.dirty == frozenset()


def test_a_full_ba_follows_the_pose_graph_after_its_every_keyframes(feed):
    f = feed(
        _config(full_ba=True, every=3, full_ba_schedule=FullBAScheduleConfig(every_keyframes=6))
    )
    core = f.core
    for i in range(3):
        f.keyframe("r0", 0.1 * i)
    out = run_inline(core, core.on_timer(1.0), 1.0)
    assert [o.kind for o in out if isinstance(o, Outcome)] == [SolveKind.POSE_GRAPH]
    assert core.full_bas == 0 and core.changed_since_full_ba(0) == 3
    for i in range(3):
        f.keyframe("r0", 2.0 + 0.1 * i)
    [req] = core.on_timer(3.0)
    actions = core.solved(req, solve(req), 3.0)
    [full] = _requests(actions)  # right after the pose graph, before the round ends
    assert (full.map_id, full.kind) == (0, SolveKind.FULL_BA) and core.busy
    assert full.full_ba is not None and full.full_ba.max_seconds == 60.0  # the solver's budget
    actions = core.solved(full, solve(full), 3.5)
    assert any(isinstance(a, SendCorrections) for a in actions)
    assert core.full_bas == 1 and core.changed_since_full_ba(0) == 0 and not core.busy


def test_quiet_maps_get_a_full_ba_quiet_s_after_the_last_keyframe(feed):
    f = feed(_config(full_ba=True, full_ba_schedule=FullBAScheduleConfig(quiet_s=2.0)))
    core = f.core
    f.keyframe("r0", 0.0)
    f.keyframe("r0", 0.4)
    assert core.next_deadline() == pytest.approx(2.4)  # no trigger: the quiet deadline
    assert core.on_timer(2.3) == []
    [req] = core.on_timer(2.4)
    assert (req.map_id, req.kind) == (0, SolveKind.FULL_BA)
    run_inline(core, [req], 2.5)
    assert core.full_bas == 1 and core.next_deadline() is None  # nothing changed since


def test_quiet_waits_while_a_pose_graph_is_scheduled(feed):
    f = feed(_config(full_ba=True, every=2, full_ba_schedule=FullBAScheduleConfig(quiet_s=1.0)))
    core = f.core
    f.keyframe("r0", 0.0)
    f.keyframe("r0", 0.1)  # triggers a pose graph at 0.6; the quiet one would be at 1.1
    assert core.next_deadline() == pytest.approx(0.6)
    [req] = core.on_timer(5.0)  # both overdue: the scheduled pose graph goes first
    assert req.kind is SolveKind.POSE_GRAPH
    core.solved(req, solve(req), 5.0)
    assert core.next_deadline() == pytest.approx(1.1)  # then the quiet full BA, at once
    assert _requests(core.on_timer(5.0))[0].kind is SolveKind.FULL_BA


@pytest.mark.parametrize("after_full_ba", [True, False])
def test_mbp_while_running_follows_a_full_ba_when_after_full_ba(feed, after_full_ba):
    f = feed(
        _config(
            full_ba=True,
            mbp=True,
            every=3,
            full_ba_schedule=FullBAScheduleConfig(every_keyframes=1000),  # never due by itself
            mbp_schedule=MbpScheduleConfig(every_keyframes=3, after_full_ba=after_full_ba),
        )
    )
    core = f.core
    for i in range(3):
        f.keyframe("r0", 0.1 * i)
    [pg] = core.on_timer(1.0)
    assert pg.kind is SolveKind.POSE_GRAPH
    full = _requests(core.solved(pg, solve(pg), 1.0))
    if after_full_ba:  # MBP is due: a full BA first, the pass after it
        assert [(r.map_id, r.kind) for r in full] == [(0, SolveKind.FULL_BA)]
        assert core.mbp_passes == 0 and core.busy
        actions = core.solved(full[0], solve(full[0]), 1.5)
        assert any(isinstance(a, SendCorrections) for a in actions)
        assert core.full_bas == 1
    else:  # the pass right after the pose graph, no full BA
        assert full == [] and core.full_bas == 0
    assert core.mbp_passes == 1 and not core.busy


@pytest.mark.parametrize("elapsed", [10.0, 31.0])
def test_shutdown_pose_graphs_then_full_ba_within_the_budget_then_mbp(feed, elapsed):
    f = feed(
        _config(
            full_ba=True,
            mbp=True,
            every=3,
            full_ba_schedule=FullBAScheduleConfig(at_shutdown_s=30.0),
        )
    )
    core = f.core
    for i in range(6):
        f.keyframe("r0", 0.1 * i)
    assert core.dirty == {0}  # scheduled, its debounce not over: shutdown comes first
    [pg] = core.shutdown(0.6)
    assert pg.kind is SolveKind.POSE_GRAPH
    actions = core.solved(pg, solve(pg), 0.6 + elapsed)
    assert any(isinstance(a, SendCorrections) for a in actions)
    full = _requests(actions)
    if elapsed < 30.0:  # the full BA gets what is left of the budget
        assert [(r.kind, r.full_ba.max_seconds) for r in full] == [
            (SolveKind.FULL_BA, pytest.approx(30.0 - elapsed))
        ]
        assert core.mbp_passes == 0  # MBP comes after the last full BA
        actions = core.solved(full[0], solve(full[0]), 0.6 + elapsed + 1.0)
        assert not any(isinstance(a, SendCorrections) for a in actions)  # not at shutdown
        assert core.full_bas == 1
    else:
        assert full == [] and core.full_bas == 0  # no time left
    assert core.mbp_passes == 1 and not core.busy


def test_cancel_schedules_the_unapplied_pose_graphs_again(feed):
    f = feed(_config(every=2))
    core = f.core
    f.keyframe("r0", 0.0)
    f.keyframe("r0", 0.1)
    [req] = core.on_timer(0.6)
    core.cancel(1.0)
    assert not core.busy and core.dirty == {0} and core.next_deadline() == pytest.approx(1.5)
    with pytest.raises(CloudCoreError):
        core.solved(req, solve(req), 1.0)  # its result no longer counts


def test_a_solve_request_runs_in_another_process_as_in_this_one(feed):
    f = feed(_config())
    for i in range(4):
        f.keyframe("r0", 0.1 * i)
    [req] = f.core.optimize(0, 1.0)
    job = pickle.loads(pickle.dumps(req.job()))
    here, there = solve(req), job()
    assert np.array_equal(here.keys, there.keys)
    assert np.allclose(here.T_world_body, there.T_world_body) and there.iterations > 0


def test_overloaded_the_due_full_ba_waits_and_runs_at_the_first_pose_graph_after(feed):
    f = feed(
        _config(full_ba=True, every=3, full_ba_schedule=FullBAScheduleConfig(every_keyframes=3))
    )
    core = f.core
    assert not core.load(0.89, 0.0) and not core.overloaded  # under OverloadConfig.busy 0.9
    assert core.status(0.0) == ""
    assert core.load(0.95, 0.0) and core.overloaded and core.overloads == 1
    assert f.app.fusion.recognizer.shed_early  # the early loop candidates shed too
    assert core.publish_every_s() == 5.0  # and the dashboard's refresh slows down
    assert core.publish_every_s(last_s=0.7) == 7.0  # (never more than ~10 % of the worker)
    for i in range(3):
        f.keyframe("r0", 0.1 * i)
    out = run_inline(core, core.on_timer(1.0), 1.0)
    assert [o.kind for o in out if isinstance(o, Outcome)] == [SolveKind.POSE_GRAPH]
    assert any(isinstance(a, SendCorrections) for a in out)  # corrections go on
    assert core.full_bas == 0 and core.full_bas_deferred == 1
    assert core.status(1.5).startswith("overloaded for 2 s: no full BA while running (1 deferred")
    assert core.changed_since_full_ba(0) == 3  # still owed
    assert not core.load(0.7, 2.0) and core.overloaded  # above OverloadConfig.clear 0.6: stays
    assert core.load(0.5, 4.0) and not core.overloaded
    assert not f.app.fusion.recognizer.shed_early
    assert core.publish_every_s() == 0.5
    assert core.publish_every_s(last_s=0.2) == pytest.approx(2.0)
    assert core.overloaded_seconds(9.0) == pytest.approx(4.0)
    for i in range(3):
        f.keyframe("r0", 5.0 + 0.1 * i)
    out = run_inline(core, core.on_timer(6.0), 6.0)
    kinds = [o.kind for o in out if isinstance(o, Outcome)]
    assert kinds == [SolveKind.POSE_GRAPH, SolveKind.FULL_BA] and core.full_bas == 1


def test_a_full_ba_deferred_by_the_overload_runs_once_it_falls_without_a_new_keyframe(feed):
    f = feed(
        _config(full_ba=True, every=3, full_ba_schedule=FullBAScheduleConfig(every_keyframes=3))
    )
    core = f.core
    core.load(0.95, 0.0)
    for i in range(3):
        f.keyframe("r0", 0.1 * i)
    out = run_inline(core, core.on_timer(1.0), 1.0)
    assert [o.kind for o in out if isinstance(o, Outcome)] == [SolveKind.POSE_GRAPH]
    assert core.full_bas_deferred == 1 and core.next_deadline() is None  # nothing scheduled
    assert core.load(0.5, 4.0) and not core.overloaded  # the last keyframe came long ago
    assert core.next_deadline() == pytest.approx(4.5)  # debounced like any trigger
    out = run_inline(core, core.on_timer(4.5), 4.5)
    kinds = [o.kind for o in out if isinstance(o, Outcome)]
    assert kinds == [SolveKind.POSE_GRAPH, SolveKind.FULL_BA] and core.full_bas == 1
    assert core.changed_since_full_ba(0) == 0 and core.next_deadline() is None


def test_overloaded_no_quiet_full_ba_but_shutdown_runs_it(feed):
    f = feed(_config(full_ba=True, full_ba_schedule=FullBAScheduleConfig(quiet_s=1.0)))
    core = f.core
    core.load(1.0, 0.0)
    f.keyframe("r0", 0.0)
    f.keyframe("r0", 0.4)
    assert core.next_deadline() is None  # the quiet full BA is not due while overloaded
    out = run_inline(core, core.shutdown(5.0), 5.0)
    assert [o.kind for o in out if isinstance(o, Outcome)] == [SolveKind.FULL_BA]
    assert core.full_bas == 1


def test_overload_busy_zero_never_sheds_and_clear_must_be_below_busy(feed):
    f = feed(_config(overload=OverloadConfig(busy=0.0, clear=0.0)))
    assert not f.core.load(1.0, 0.0) and not f.core.overloaded
    with pytest.raises(ValueError, match="clear"):
        OverloadConfig(busy=0.5, clear=0.6)


def test_a_full_ba_cut_short_by_the_stop_still_runs_at_shutdown(feed):
    # The service stops while a quiet full BA is out: the round is cancelled, its result never
    # comes back, and the shutdown must still run a full BA of that map (it had changes).
    f = feed(_config(full_ba=True, full_ba_schedule=FullBAScheduleConfig(quiet_s=1.0)))
    core = f.core
    f.keyframe("r0", 0.0)
    f.keyframe("r0", 0.4)
    assert core.changed_since_full_ba(0) > 0
    [quiet] = _requests(core.on_timer(2.0))
    assert quiet.kind is SolveKind.FULL_BA and core.changed_since_full_ba(0) == 0
    core.cancel(2.5)
    assert not core.busy and core.changed_since_full_ba(0) > 0  # owed again
    out = run_inline(core, core.shutdown(3.0), 3.0)
    assert [(o.kind, o.applied) for o in out if isinstance(o, Outcome)] == [
        (SolveKind.FULL_BA, True)
    ]
    assert core.full_bas == 1


def test_a_failed_full_ba_solve_is_owed_to_the_next_occasion(feed):
    f = feed(_config(full_ba=True, full_ba_schedule=FullBAScheduleConfig(quiet_s=1.0)))
    core = f.core
    f.keyframe("r0", 0.0)
    f.keyframe("r0", 0.4)
    owed = core.changed_since_full_ba(0)
    [quiet] = _requests(core.on_timer(2.0))
    assert core.failed(quiet, 2.5) == [] and not core.busy
    assert core.changed_since_full_ba(0) == owed
    out = run_inline(core, core.shutdown(3.0), 3.0)
    assert [o.kind for o in out if isinstance(o, Outcome)] == [SolveKind.FULL_BA]
    assert core.full_bas == 1

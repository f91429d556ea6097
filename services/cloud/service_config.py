"""Options of the cloud network service, one frozen dataclass per concern, nested in
:class:`CloudServiceConfig`: built once at the entry point (``services/cloud/runner.py``) and
handed down. The map work's own options are :class:`services.cloud.config.CloudConfig`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from common.links import WireFormat
from services.cloud.config import CloudConfig, MbpConfig


@dataclass(frozen=True)
class OptimizationScheduleConfig:
    """When a map's optimisation round runs: a pose graph, then a full BA or an MBP pass when
    due (:class:`services.cloud.core.CloudCore`).

    every_keyframes: a map is optimised after this many new keyframes even without a loop or
        merge (default 25); a verified loop or merge schedules it at once.
    debounce_s: after a trigger, wait this long so that a burst of triggers costs one round
        (default 0.5 s).
    rest_factor: a scheduled round starts no sooner than this many times the last round's
        duration after its end (default 1.0: the rounds take at most about half of the time,
        whatever the map's size, and the messages the rest; a small map's rounds are shorter
        than ``debounce_s``, which rules then).
    """

    every_keyframes: int = 25
    debounce_s: float = 0.5
    rest_factor: float = 1.0


@dataclass(frozen=True)
class FullBAScheduleConfig:
    """When a map gets a full bundle adjustment, with ``CloudConfig.full_ba.enabled``
    (:class:`services.cloud.core.CloudCore`).

    every_keyframes: right after the map's pose graph once it has this many new keyframes
        since its last full BA (loops and merges count too; default 100) ...
    quiet_s: ... and when no new keyframe has arrived and nothing is scheduled for this long
        while the map changed since its last one (0 = never on quiet; default 0: on the
        recorded 3-robot run, 17x slower than real time, 10 s fired 31 full BAs and the
        open-loop replay's joint ATE went 5.5 -> 6.4 cm, while every 100 keyframes and at
        shutdown gave 2.5 cm (at shutdown only: 1.4 cm, but no full BA reaches the robots
        while they run); benchmarks/results/cloud_full_ba.md) ...
    at_shutdown_s: ... and once at shutdown, before the trajectories are written, after the
        pending pose graphs, within this many seconds in all (default 30 s: the
        orchestration's stop waits 120 s; 0 = not at shutdown).
    """

    every_keyframes: int = 100
    quiet_s: float = 0.0
    at_shutdown_s: float = 30.0


def _running_mbp() -> MbpConfig:
    """The default options of a pass while running (:class:`MbpScheduleConfig`)."""
    return MbpConfig(cover_ratio=0.8, min_observations=1, max_interval_s=1.5)


@dataclass(frozen=True)
class MbpScheduleConfig:
    """When MBP prunes a map, with ``CloudConfig.mbp.enabled``, and how a pass while the
    robots run differs from the one at shutdown (``services/cloud/app_optimization.py``).

    every_keyframes: a pass runs on a map after this many new keyframes since its last pass,
        right after an optimisation (0 = never while running; default 0: live, every 40 kept
        18-34 % of the keyframes at -31 / -50 / +17 % mean joint ATE against runs without it
        on seeds 0 / 1 / 2, six runs each (ten on seed 2), benchmarks/results/mbp_live.md;
        replays of six recordings -0.7 % mean, both of seed 2 worse, all of it the map's
        scale, benchmarks/results/mbp_midrun.md) ...
    at_shutdown: ... and over every map at shutdown with ``CloudConfig.mbp``'s options, after
        the last full BA, before the trajectories are written (default True): the persisted
        map is the pruned one.
    keep_recent: each agent's newest keyframes a pass never removes (default 5) ...
    settle_keyframes: ... and, in a pass while running, each agent's this many newest
        keyframes (default 30): they are still in the edge's reach (it keeps re-sending their
        poses and their young points keep moving), and pruning them folds and freezes
        unsettled geometry (protecting 5 instead raised the replays' joint ATE 3-7x).
    after_full_ba: with full BA on, a pass while running waits for a full BA: the pose graph
        that finds MBP due schedules a full BA of the map at once, and the pass runs right
        after that is applied (default True). A pose graph moves the keyframes and each map
        point only with its reference keyframe, so right after one the points seen across a
        loop are where the loop left them; a pass then folds that geometry into the
        absorbing keyframes' virtual observations. Costs one more full BA per pass.
    running: the options of a pass while running. What it keeps must carry the later loops
        and full BAs, so it prunes less than the pass at shutdown (``CloudConfig.mbp``):

        - ``cover_ratio`` 0.8 (0.5 at shutdown): on replays of recordings of seeds 1 and 2
          with loops that do not fuse their points, against no pruning, 0.5 kept 54 / 31 % of
          the keyframes at +4.4 / +2.6 % joint ATE, 0.7 kept 55 / 34 % at +2.3 / -6.1 %, 0.8
          kept 57 / 34 % at +1.1 / -14 %;
        - ``min_observations`` 1 (2 at shutdown): only the points left without an observer
          go. A point left with one constrains nothing now, but a later keyframe, loop or
          merge can observe it again. On replays of recordings of seeds 0 and 1, culling at 2
          was +7.6 / +15.5 % joint ATE against no pruning, keeping them (with coverage
          counted on the points two keyframes see) +3.8 / -0.8 %;
        - ``max_interval_s`` 1.5 s (no limit at shutdown, after the last full BA): above the
          full BA's ``imu_max_interval_s`` (3 s) the full BAs after the pass bridge an
          interval with the weak relative-pose stand-in only, not with the IMU (a seed-1
          replay's last full BA had 7 such gaps). On replays of recordings of seeds 0 / 1 / 2
          with loops fusing their points, joint ATE 0.18 / 0.28 / 0.45 cm without pruning,
          0.24 / 0.32 / 0.76 with no limit, 0.17 / 0.29 / 0.61 with 3 s, 0.15 / 0.26 / 0.55
          with 1.5 s (the rest of seed 2's gap is the map's scale: Sim(3) 0.12 cm either way);
        - the rest as ``MbpConfig``'s defaults. ``enabled`` False: no pass while running.
    """

    every_keyframes: int = 0
    at_shutdown: bool = True
    keep_recent: int = 5
    settle_keyframes: int = 30
    after_full_ba: bool = True
    running: MbpConfig = field(default_factory=_running_mbp)


@dataclass(frozen=True)
class OverloadConfig:
    """When the cloud sheds the work that only refines (:class:`services.cloud.core.CloudCore`).

    busy: the cloud is *overloaded* once its worker thread was busy (wall time, waiting for
        the core included) at least this share of the last ``window_s`` (default 0.9; 0 =
        never overloaded). While it is, no full BA runs while running (nor the MBP pass that
        waits for one; both run once the load falls, and at shutdown), only consistent loop
        candidates are verified (no ``PlaceRecognitionConfig.early_candidates``), and the
        dashboard's map view is refreshed every ``publish_every_s`` at most. Messages, pose
        graphs and their corrections go on as always ...
    clear: ... until the busy share falls to this (default 0.6) ...
    window_s: ... over this many seconds (default 10 s).
    publish_every_s: the map view's refresh period while overloaded, at least (default 5 s:
        its atlas snapshot took ~0.2 s of the worker at 12 agents, ~400k points;
        benchmarks/results/scale.md).
    """

    busy: float = 0.9
    clear: float = 0.6
    window_s: float = 10.0
    publish_every_s: float = 5.0

    def __post_init__(self) -> None:
        if self.busy and not 0 <= self.clear < self.busy <= 1:
            raise ValueError(
                "overload: need 0 <= clear < busy <= 1 (or busy 0), got "
                f"clear {self.clear} and busy {self.busy}"
            )
        if self.window_s <= 0:
            raise ValueError(f"overload window_s must be > 0, got {self.window_s}")


@dataclass(frozen=True)
class MapViewConfig:
    """The dashboard's view of the atlas (``services/cloud/store/map_source.py``).

    publish_every_s: the view is refreshed this often (default 0.5 s; 0 = never: no dashboard
        reads it, and the atlas snapshot it takes on the worker grows with the map, 66 ms per
        refresh at 3 agents in benchmarks/results/scale.md) ...
    publish_rest_factor: ... and no sooner than this many times the last refresh's duration
        after it (default 10: the refreshes take at most ~10 % of the worker; 0.21 s at 12
        agents, ~400k points, then every 2.1 s).
    gt_every_s: with ground truth, the reference trajectories are re-aligned to the maps
        this often (default 5 s).
    bandwidth_window_s: bandwidth samples kept (default 120 s).
    display_spacing_m: maps that are not merged yet are shown side by side, this far apart
        along x (default 0 m: each in its own frame, overlapping).
    """

    publish_every_s: float = 0.5
    publish_rest_factor: float = 10.0
    gt_every_s: float = 5.0
    bandwidth_window_s: float = 120.0
    display_spacing_m: float = 0.0


@dataclass(frozen=True)
class StoreConfig:
    """The state directory's mission and the result files (``services/cloud/store/``).

    mission: the named mission to serve (``services.cloud.store.mission``): resumed when it
        is the state directory's current one, else started, the earlier missions' agents
        becoming the read-only prior map (default None: the current mission continues).
    output_every_s: trajectories (and the ATE report) are rewritten this often (default 30 s;
        0 = only at shutdown).
    """

    mission: str | None = None
    output_every_s: float = 30.0


@dataclass(frozen=True)
class ProcessConfig:
    """The helper processes beside the worker thread that applies the edges' messages.

    optimizer_process: solve in a separate process (default True: gtsam holds the GIL during
        most of a solve, which would stall the event loop's thread;
        benchmarks/results/cloud_service.md); False uses a thread (no process start-up, fine
        for small maps).
    optimizer_nice: the optimizer process's niceness increment (``os.nice``; 0-19; default 0:
        the service's priority). Higher gives a core shared by the worker and the solver to
        the worker first (nice 10: ~9x the solver's share while both run). On 12 agents at
        one core (benchmarks/results/scale.md), nice 10 against 0: queue peak 1995 vs 2600
        messages, drained 31 vs 58 s after the end, but 52 vs 88 % of the keyframes
        corrected before it; an overloaded cloud then takes the edges' messages faster and
        corrects the robots less, so 0 is the default.
    decode_workers: decode the keyframes' features in this many helper processes before the
        worker applies them (default 0: on the worker). The worker applies every message in
        turn on one thread, and a 1000-feature keyframe's decode is ~25 ms of it; with
        workers it overlaps the worker's other messages on other cores (no help on one core;
        benchmarks/results/scale.md).
    """

    optimizer_process: bool = True
    optimizer_nice: int = 0
    decode_workers: int = 0

    def __post_init__(self) -> None:
        if not 0 <= self.optimizer_nice <= 19:
            raise ValueError(f"optimizer_nice must be in 0..19, got {self.optimizer_nice}")
        if self.decode_workers < 0:
            raise ValueError(f"decode_workers must be >= 0, got {self.decode_workers}")


@dataclass(frozen=True)
class CloudServiceConfig:
    """Options of the cloud network service (``services/cloud/server.py``), built once at the
    entry point (``services/cloud/runner.py``) and handed down.

    wire: how corrections go to the edges (``PoseCorrectionCoded``; ``raw``: the schema-1
        float64 ``PoseCorrection``).
    domain: the map work itself (:class:`CloudConfig`).
    word_group_level: verification matches words within their vocabulary ancestor at this
        tree level (None = same word only; default 3 of a k=10, L=4 vocabulary, so that a
        few flipped descriptor bits that change the leaf do not lose the match).
    schedule, full_ba, mbp: when the pose graph, the full BA and MBP run.
    overload: when the optimisations that only refine are shed.
    map_view: the dashboard's view of the atlas.
    store: the mission served and the result files.
    processes: the optimizer and decode processes.
    """

    wire: WireFormat = WireFormat.CODED
    domain: CloudConfig = field(default_factory=CloudConfig)
    word_group_level: int | None = 3
    schedule: OptimizationScheduleConfig = field(default_factory=OptimizationScheduleConfig)
    full_ba: FullBAScheduleConfig = field(default_factory=FullBAScheduleConfig)
    mbp: MbpScheduleConfig = field(default_factory=MbpScheduleConfig)
    overload: OverloadConfig = field(default_factory=OverloadConfig)
    map_view: MapViewConfig = field(default_factory=MapViewConfig)
    store: StoreConfig = field(default_factory=StoreConfig)
    processes: ProcessConfig = field(default_factory=ProcessConfig)

"""Plain data of the edge VIO: options (documented defaults), inputs and outputs.

Frame rule: ``T_a_b`` maps points of frame ``b`` into frame ``a``. The body frame is the IMU
frame; ``world`` is the map frame of one map (gravity-aligned, ``g_world = (0, 0, -g)``, once
visual-inertial initialisation has run; an arbitrary first-keyframe frame before). Units: metres,
seconds (timestamps in int64 nanoseconds), radians, pixels where a name says ``px``.
"""

from __future__ import annotations

import dataclasses
import enum
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from common.errors import RecslamError
from services.edge.vio.time_offset import TimeOffsetConfig


class VioError(RecslamError):
    """Invalid input given to the edge VIO (names the offending field)."""


class TrackingStatus(enum.Enum):
    """Per-frame state of one robot's VIO."""

    INITIALIZING = "initializing"  # no metric map yet (mono or visual-inertial init pending)
    TRACKING = "tracking"  # pose in a metric, gravity-aligned map
    LOST = "lost"  # tracking failed on this frame; a new map is started


# ------------------------------------------------------------------------------ options


@dataclass(frozen=True)
class MonoInitConfig:
    """Two-view initialisation (ORB-SLAM-like model selection between E and H)."""

    min_tracks: int = 60  # shared tracks needed between reference and current keyframe
    min_triangulated: int = 50  # points with good parallax needed to accept
    min_parallax_deg: float = 1.0  # per-point parallax for a point to count
    min_median_parallax_deg: float = 3.0  # median parallax of the triangulated set
    ransac_threshold_px: float = 1.5  # epipolar / homography RANSAC threshold
    homography_ratio: float = 0.45  # choose H when S_H / (S_H + S_F) exceeds this
    max_reference_age_s: float = 2.0  # replace the reference keyframe when older than this


@dataclass(frozen=True)
class ViInitConfig:
    """Inertial-only MAP initialisation (ORB-SLAM3) and its later refinements."""

    first_after_s: float = 2.0  # map age before the first VI initialisation
    min_keyframes: int = 10  # keyframes needed for the first VI initialisation
    # Map ages of the re-runs (joint VI BA over every keyframe: scale, gravity, biases). Early
    # ones matter: a first init in a hovering start can be 40-60 % off in scale (seed 1). Late
    # ones (25-50 s, like ORB-SLAM3's scale refinements up to 75 s) stop the slow scale drift
    # of weakly excited robots: seed 1 robot0 drifted to -4.5 % local scale by 40 s without.
    refine_after_s: tuple[float, ...] = (4.0, 7.0, 10.0, 15.0, 25.0, 35.0, 50.0)
    gyro_bias_prior_sigma_first: float = 0.1  # rad/s (ORB-SLAM3 priorG = 1e2)
    # m/s². ORB-SLAM3's priorA = 1e10 holds the bias at 0 in the first init; with the synthetic
    # IMUs' 0.05-0.12 m/s² biases and a weakly accelerating start that gave seed 1 robot0 a
    # scale 38 % short (first 2 s); 0.1 gives 2 % (all 9 robots of three seeds within 6 %).
    accel_bias_prior_sigma_first: float = 0.1
    gyro_bias_prior_sigma: float = 1.0  # rad/s, re-runs (priorG = 1)
    # m/s², re-runs. ORB-SLAM3's priorA = 1e5 (3.16e-3) held the accel bias near 0 and the
    # scale absorbed the synthetic IMUs' 0.05-0.12 m/s² biases (scale -19 % on seed 1 robot0).
    accel_bias_prior_sigma: float = 0.1
    min_interval_s: float = 0.5  # keyframes are subsampled to this spacing for the MAP problem
    # Pose noise of the visual map as a fraction of the median scene depth: 0.002 rejected
    # every first init on LK-tracked rendered images (cost/residual 0.3-1.5 for 15 s).
    visual_position_sigma_rel: float = 0.01
    visual_rotation_sigma_deg: float = 0.1  # pose rotation noise of the visual map
    max_span_s: float = 4.0  # the inertial-only problem uses the newest keyframes of this span
    retry_interval_s: float = 0.5  # after a rejected attempt, wait this long (map time)
    max_cost_per_residual: float = 0.25  # reject (retry at the next keyframe) above this ...
    # ... or above this when the IMU is weighted by the noise it shows (a real sensor's
    # vibration, VioConfig.noise_from_data): then the whitened residuals are as the model
    # says, about 1 each (V2_01/02/03's real IMUs: 0.5-1.6), where the datasheet-clean
    # generator's IMU, its visual pose noise overstated, gives 0.1-0.25.
    max_cost_per_residual_measured_noise: float = 2.0
    min_scale: float = 1e-3  # a smaller/larger scale estimate is rejected
    max_scale: float = 1e3
    full_ba_iterations: int = 30  # joint visual-inertial refinement after each run
    # While the camera-IMU offset is estimated online, the first VI initialisation waits up to
    # this long (map time) beyond first_after_s for a confident estimate (0: it does not wait).
    # An init on IMU segments 15 ms out of step starts the map with a scale and biases the
    # refinements only partly undo (real V2 flights: robot2 6.3 -> 3.2 cm from 8 s on, robot0
    # and robot1 equal); the price is a first init ~5 s later (6.9-7.9 s after motion there).
    wait_for_time_offset_s: float = 0.0
    # A first VI initialisation without a confident offset takes an estimate made then whose
    # sigma is within time_offset.max_sigma_ms (it lacks only the span) when the offset in use
    # lies more than this many of its sigmas (0: never) and adopt_time_offset_min_ms from it: a
    # 15 ms offset unknown, estimated at 16.1 ± 0.1 ms over the map's first 3 s, must not start
    # the map with the IMU read 15 ms out of step (real V2_03: edge VIO 4.3 -> 3.6 cm). The
    # floor: over so short a span the sigma understates the error by a few ms.
    adopt_time_offset_sigmas: float = 3.0
    adopt_time_offset_min_ms: float = 5.0
    # A VI-initialised map whose camera-IMU offset moved by this much [ms] since its last VI
    # (re)solve is refined at once (the IMU between its keyframes was re-sliced) rather than
    # at the next age of refine_after_s (0: never). Real V2 flights with a 15 ms offset found
    # ~12 s after motion: robot2 6.3 -> 3.9 cm from 8 s on; synchronised ones do not move.
    refine_on_offset_change_ms: float = 2.0


@dataclass(frozen=True)
class TrackingConfig:
    """Per-frame pose tracking (PnP RANSAC, then motion-only optimisation)."""

    min_inliers: int = 15  # fewer inliers: tracking lost, a new map is started
    chi2_threshold: float = 5.991  # 2-DoF 95 % inlier gate on whitened reprojection error
    ransac_threshold_px: float = 3.0
    ransac_iterations: int = 100
    prior_inlier_ratio: float = 0.6  # IMU-predicted pose is trusted (RANSAC skipped) above this
    max_iterations: int = 8  # motion-only optimisation iterations
    # A VI-initialised map whose tracking fails is kept this long [s] while the IMU predicts
    # the pose (ORB-SLAM3's RECENTLY_LOST time, 5 s): each robot keyframe meanwhile has its
    # ORB features searched in the local map by projection from that prediction (window
    # ``relocalise_radius_scale`` × the mapping's radius) and is tracked again, and frames
    # within ``imu_bridge_s`` of the map's last keyframe are bridged (``bridge_while_lost``);
    # only then is a new map started. 0: a failure starts a new map at once. (3 s before
    # bridging while lost: a 50 kbit/s robot's next frames came 2.5 s later, too late.)
    recently_lost_s: float = 5.0
    # Too few tracks with map points but the IMU recent: a frame within this long [s] of its
    # map's last keyframe becomes a keyframe at the IMU's prediction, its tracks triangulated
    # and refined by the visual-inertial local BA (VINS-style), before the map counts as
    # lost (0: never). 3 s: the longest gap an uplink budget leaves between the frames it
    # sends (at 50 kbit/s the fastest robot's keyframes, ~7 kB, come 1.3-2.6 s apart with
    # little between), over which the IMU alone, with the map's biases, drifts ~10 cm
    # (0.5 × 0.02 m/s² × (3 s)² + 0.01 m/s × 3 s): a starting point for the VI local BA.
    imu_bridge_s: float = 3.0
    # While a VI map is recently lost, a frame within ``imu_bridge_s`` of the map's last
    # keyframe is bridged too, from the keyframe a failed bridge left (too few points): a
    # robot that turned to new ground between two sparse keyframes shares tracks with it,
    # which are triangulated between their IMU poses. False: a failed bridge ends bridging
    # until the map is tracked again (or a new map starts).
    bridge_while_lost: bool = True
    # A bridge places its keyframe from the IMU alone only while the position the IMU
    # predicts since the newest keyframe the map held stays within this [m] (1 sigma, under
    # the accelerometer noise the VIO weighs the IMU by; 0: no bound): about the window the
    # map's points are searched in by projection (30 px at 3 m depth). The generator's IMU
    # (0.002 m/s^2/sqrt(Hz)) bridges for the whole recently lost time; a real MAV's in
    # flight (~0.1, vibration) ~2 s (the real V2 flights at 50 kbit/s, replayed: chains of
    # bridges 5-8 s long on their IMU left a robot's VIO 48 cm off).
    bridge_max_sigma_m: float = 0.2
    relocalise_radius_scale: float = 2.0


@dataclass(frozen=True)
class MappingConfig:
    """Keyframe processing: triangulation of new map points and culling."""

    min_parallax_deg: float = 1.0  # between the first and last observing keyframe
    max_reprojection_chi2: float = 5.991  # a new point must reproject within this everywhere
    min_depth_m: float = 0.05  # in map units (arbitrary before VI init)
    cull_chi2: float = 9.21  # observations worse than this are removed after local BA
    min_observations: int = 2  # points with fewer keyframe observations are removed
    match_by_projection: bool = True  # bind new keyframe features to existing map points
    match_radius_px: float = 15.0  # search radius at level 0 (× 1.2^level)
    match_max_hamming: int = 50  # ORB descriptor distance accepted (of 256 bits)
    match_ratio: float = 0.8  # best / second-best descriptor distance
    match_keyframes: int = 20  # local map searched: points seen by this many newest keyframes


@dataclass(frozen=True)
class LocalBAConfig:
    """Local bundle adjustment (paper Eq. 18, Fig. 5b)."""

    window_size: int = 10  # newest keyframes optimised; older observers are fixed
    cauchy_k: float = 2.4477  # on whitened reprojection error (sqrt(5.991))
    imu_huber_k: float = 5.0  # whitened 15-DoF IMU error: sqrt(chi2_15(0.95)) = sqrt(25.0)
    max_iterations: int = 5
    relative_error_tol: float = 1e-3  # LM stops when the cost falls by less than this share
    max_fixed_observers: int = 5  # observers outside the window kept as fixed poses
    fixed_sigma: float = 1e-6  # prior sigma holding fixed variables
    # "schur": Schur-complement LM with the reprojection terms in numpy (ba_solver.py);
    # "gtsam": one gtsam graph and its LM (the reference; same problem, same LM schedule).
    solver: str = "schur"
    # ... "schur" up to this many free keyframes, gtsam beyond (an escape hatch; no limit in
    # practice). The Schur solver keeps its reduced camera system sparse above 20 keyframes
    # (ba_sparse.py), so the VI refinements over every keyframe use it too: the last one of
    # seed 1 robot0 (231 keyframes, 28.7k points) 3.7 -> 1.9 s CPU with this path
    # (benchmarks/results/vi_refinement.md).
    schur_max_keyframes: int = 100_000
    # Cost caps (CPU is the edge's budget: three robots' VIO share two cores). A local BA runs
    # on every robot keyframe and on every ``every_keyframes``-th of the VIO's own ones ...
    every_keyframes: int = 3
    # ... over at most this many points (those with the most observations in the window;
    # 0: all). Points left out keep their position until a later window takes them.
    max_points: int = 1500
    # Measured on the rendered 3×60 s dataset through the real pipeline (robot0/1/2): with
    # every keyframe, 10 iterations, 20 fixed observers and all points: 63/53/54 ms CPU per
    # frame, ATE 1.7/2.8/5.0 cm; with these defaults: 27/27/29 ms, ATE 1.8/3.4/6.1 cm.
    # solver "schur" vs "gtsam" (3 seeds × 3 robots, same inputs, commit 7470d71): same ATE
    # and scale error on all 9 robots; one local BA (10 keyframes, 1500 points) 170 -> 53 ms
    # CPU; VIO CPU 31-34 -> 21-22.5 ms per frame (seed 2 robot2: 49 -> 32).

    def __post_init__(self) -> None:
        if self.solver not in ("schur", "gtsam"):
            raise VioError(f"LocalBAConfig.solver: {self.solver!r} (expected 'schur' or 'gtsam')")


@dataclass(frozen=True)
class VioConfig:
    """Every option of one robot's VIO. Defaults suit EuRoC-like data at 20 Hz."""

    gravity_mps2: float = 9.81
    pixel_sigma: float = 1.0  # px at pyramid level 0; level l uses pixel_sigma * 1.2**l
    level_scale: float = 1.2
    integration_sigma: float = 1e-4  # preintegration integration noise (m/s²/√Hz-like)
    min_keyframe_interval_s: float = 0.05  # robot keyframes closer than this are not inserted
    # The VIO's own keyframes on non-keyframe frames (no descriptors): robots that send a
    # keyframe only every ~1 s leave too little shared structure between keyframes. A frame
    # becomes one when this long passed since the last keyframe (0: never) ...
    max_keyframe_interval_s: float = 0.25
    # ... or when fewer tracks than this share of the last keyframe's map points are inliers.
    min_tracked_point_ratio: float = 0.5
    # Weigh the IMU by the white noise it shows (measured over the newest
    # ``noise_window_samples``) where that exceeds its calibration 1.5-fold or more: real
    # vibration (VINS-Fusion's EuRoC file raises the datasheet ~50x by hand; this measures it).
    noise_from_data: bool = True
    noise_window_samples: int = 2000
    imu_history_s: float = 65.0  # IMU kept for the noise, the time offset and re-slicing
    # Camera-IMU time offset (t_imu = t_cam + offset, ns): the calibration's, and whether the
    # VIO estimates it online from its frames' rotations and the gyro (time_offset.py).
    time_offset_ns: int = 0
    estimate_time_offset: bool = True
    time_offset: TimeOffsetConfig = field(default_factory=TimeOffsetConfig)
    mono_init: MonoInitConfig = field(default_factory=MonoInitConfig)
    vi_init: ViInitConfig = field(default_factory=ViInitConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    local_ba: LocalBAConfig = field(default_factory=LocalBAConfig)


# ------------------------------------------------------------------------------ inputs


def _readonly(a: object, dtype: type, shape_tail: tuple[int, ...], name: str) -> np.ndarray:
    arr = np.asarray(a)
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        raise VioError(
            f"FrameObservation.{name}: expected shape (N, *{shape_tail}), got {arr.shape}"
        )
    arr = np.array(arr, dtype=dtype)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class FrameObservation:
    """One decoded robot frame.

    ``track_ids`` (N,) int64, persistent per robot (same physical feature, same id while
    tracked); ``keypoints_px`` (N, 2) float64 DISTORTED pixel coordinates; ``levels`` (N,)
    uint8 pyramid level (noise sigma 1.2**level px); ``descriptors`` (N, 32) uint8 ORB on robot
    keyframes, else None.
    """

    timestamp_ns: int
    track_ids: np.ndarray
    keypoints_px: np.ndarray
    levels: np.ndarray
    is_keyframe: bool = False
    descriptors: np.ndarray | None = None

    def __post_init__(self) -> None:
        ids = _readonly(self.track_ids, np.int64, (), "track_ids")
        kps = _readonly(self.keypoints_px, np.float64, (2,), "keypoints_px")
        lv = _readonly(self.levels, np.uint8, (), "levels")
        n = len(ids)
        if len(kps) != n or len(lv) != n:
            raise VioError(
                f"FrameObservation: track_ids has {n} rows, keypoints_px {len(kps)}, "
                f"levels {len(lv)}"
            )
        if len(np.unique(ids)) != n:
            raise VioError("FrameObservation.track_ids: duplicate track id in one frame")
        if not np.all(np.isfinite(kps)):
            raise VioError("FrameObservation.keypoints_px: non-finite coordinate")
        object.__setattr__(self, "track_ids", ids)
        object.__setattr__(self, "keypoints_px", kps)
        object.__setattr__(self, "levels", lv)
        object.__setattr__(self, "timestamp_ns", int(self.timestamp_ns))
        object.__setattr__(self, "is_keyframe", bool(self.is_keyframe))
        if self.descriptors is not None:
            d = _readonly(self.descriptors, np.uint8, (32,), "descriptors")
            if len(d) != n:
                raise VioError(f"FrameObservation.descriptors has {len(d)} rows, expected {n}")
            object.__setattr__(self, "descriptors", d)

    def subset(self, keep: np.ndarray) -> FrameObservation:
        """This frame with only the features of mask ``keep`` (N,)."""
        return dataclasses.replace(
            self,
            track_ids=self.track_ids[keep],
            keypoints_px=self.keypoints_px[keep],
            levels=self.levels[keep],
            descriptors=None if self.descriptors is None else self.descriptors[keep],
        )


# ------------------------------------------------------------------------------ outputs


@dataclass(frozen=True, eq=False)
class FrameResult:
    """Outcome of one ``feed_frame``. ``T_world_body`` (4, 4) is identity while no map exists;
    before VI initialisation it is in the arbitrary-scale visual map frame."""

    timestamp_ns: int
    T_world_body: np.ndarray
    status: TrackingStatus
    map_id: int
    n_inliers: int
    is_new_keyframe: bool
    reason: str = ""  # why INITIALIZING / LOST, for logs and reports


@dataclass(frozen=True, eq=False)
class VioState:
    """The VIO's inertial state at a frame, the content of the feedback for the robot's
    IMU-aided tracker (only valid after VI initialisation). Not the robot's
    ``services.robot.imu_prediction.InertialState``, which holds what the robot applies.

    ``v_world`` (3,) m/s; ``bias_gyro`` (3,) rad/s; ``bias_accel`` (3,) m/s²;
    ``gravity_body`` (3,) m/s², gravity expressed in the body (IMU) frame at ``timestamp_ns``.
    """

    timestamp_ns: int
    map_id: int
    T_world_body: np.ndarray
    v_world: np.ndarray
    bias_gyro: np.ndarray
    bias_accel: np.ndarray
    gravity_body: np.ndarray


@dataclass(frozen=True, eq=False)
class KeyframeSnapshot:
    """A keyframe for the uplink. ``track_ids`` (N,) are its features in robot order (-1 for
    one the VIO left out); ``point_ids`` (N,) the map point of each feature or -1."""

    keyframe_id: int
    map_id: int
    timestamp_ns: int
    T_world_body: np.ndarray
    v_world: np.ndarray
    bias_gyro: np.ndarray
    bias_accel: np.ndarray
    track_ids: np.ndarray
    point_ids: np.ndarray
    previous_keyframe_id: int | None
    # False for the VIO's own keyframes (made of non-keyframe frames: no robot features, no
    # descriptors); the uplink has no features to send for those.
    robot_keyframe: bool = True


@dataclass(frozen=True, eq=False)
class MapPointSnapshot:
    """A map point for the uplink: ``p_world`` (3,) m; observed by ``keyframe_ids`` (K,) at
    row ``feature_indices`` (K,) of each keyframe's features."""

    point_id: int
    map_id: int
    p_world: np.ndarray
    keyframe_ids: np.ndarray
    feature_indices: np.ndarray


@dataclass(frozen=True, eq=False)
class MapPointBatch:
    """Map points for the uplink as flat arrays (cheap to pickle between processes: a
    per-point object costs ~20 µs to unpickle, 1500 points per update): ``point_ids`` (P,),
    ``p_world`` (P, 3) m, ``counts`` (P,) observations per point, and the observations in
    point order: ``keyframe_ids`` (O,), ``feature_indices`` (O,) (row of each keyframe's
    features), O = counts.sum()."""

    point_ids: np.ndarray
    p_world: np.ndarray
    counts: np.ndarray
    keyframe_ids: np.ndarray
    feature_indices: np.ndarray

    def __len__(self) -> int:
        return len(self.point_ids)

    @staticmethod
    def of(points: Sequence[MapPointSnapshot]) -> MapPointBatch:
        """The batch of these snapshots (in order)."""
        n = len(points)
        return MapPointBatch(
            point_ids=np.fromiter((p.point_id for p in points), np.int64, n),
            p_world=np.array([p.p_world for p in points], np.float64).reshape(n, 3),
            counts=np.fromiter((len(p.keyframe_ids) for p in points), np.int64, n),
            keyframe_ids=np.concatenate([[], *(p.keyframe_ids for p in points)]).astype(np.int64),
            feature_indices=np.concatenate([[], *(p.feature_indices for p in points)]).astype(
                np.int64
            ),
        )


@dataclass(frozen=True, eq=False)
class MapUpdate:
    """What changed in one map since the previous ``pop_map_update``."""

    map_id: int
    vi_initialized: bool
    keyframes: tuple[KeyframeSnapshot, ...]
    points: MapPointBatch
    removed_point_ids: tuple[int, ...]


@dataclass
class VioStats:
    """Wall-clock durations [s] of the stages, for benchmarks (not used by the estimator);
    the IMU white-noise densities (gyro rad/s/√Hz, accel m/s²/√Hz) measured on the newest
    samples and those the preintegration uses (NaN before the first VI initialisation); the
    camera-IMU time offset in use [ms] and its last estimate's sigma."""

    track_s: list[float] = field(default_factory=list)
    local_ba_s: list[float] = field(default_factory=list)
    vi_init_s: list[float] = field(default_factory=list)
    maps_started: int = 0
    frames_lost_kept: int = 0  # frames not tracked while their map was kept (recently lost)
    relocalised: int = 0  # recently lost maps tracked again (by a keyframe's descriptors)
    frames_bridged: int = 0  # frames made keyframes at the IMU's prediction (too few points)
    bridged_back: int = 0  # recently lost maps tracked again by a bridge
    imu_noise_measured: tuple[float, float] = (float("nan"), float("nan"))
    imu_noise_used: tuple[float, float] = (float("nan"), float("nan"))
    time_offset_ms: float = 0.0  # the offset in use (t_imu = t_cam + offset)
    time_offset_sigma_ms: float = float("nan")  # of the last estimate (NaN: none yet)

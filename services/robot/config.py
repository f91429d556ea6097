"""Options of the robot's front end (IMU-assisted LK tracking, ORB keyframes, keyframe decision).

Every options struct is a frozen dataclass with documented defaults; one
:class:`FrontEndConfig` is built once and handed down. Baselines of the paper's comparisons are
flags here, so that the same code runs both sides of every figure.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field


class PredictionMode(enum.Enum):
    """Initial guess for LK in the new frame."""

    IMU = "imu"
    """Gyro rotation before VI initialisation, propagated edge state after it (the paper)."""
    NONE = "none"
    """Plain LK baseline: the initial guess is the previous position."""


class RansacModel(enum.Enum):
    """Two-view model RANSAC fits to drop outlier tracks (both on undistorted points)."""

    FUNDAMENTAL = "fundamental"
    """8-point F on undistorted pixels: same inliers as E here at ~1/7 of the time."""
    ESSENTIAL = "essential"
    """5-point E on normalised coordinates."""


class TrackingMode(enum.Enum):
    """How correspondences between consecutive frames are found."""

    OPTICAL_FLOW = "optical_flow"
    """Pyramidal LK on non-keyframes, ORB only on keyframes (the paper)."""
    ORB_MATCHING = "orb_matching"
    """Baseline: ORB extracted on every frame and matched by descriptor to the previous one."""


@dataclass(frozen=True)
class OrbConfig:
    """ORB extraction on keyframes (defaults as ORB-SLAM3 on EuRoC).

    The image is split into ``grid_cols`` × ``grid_rows`` cells; OpenCV's ORB detects
    ``oversample`` × ``n_features`` candidates and each cell keeps its strongest share, so the
    features spread over the image as ORB-SLAM's quadtree intends.
    """

    n_features: int = 1000
    """Features per keyframe."""
    n_levels: int = 8
    """Scale pyramid levels (keypoint level σ in 0..n_levels-1)."""
    scale_factor: float = 1.2
    """Scale between pyramid levels."""
    fast_threshold: int = 20
    """FAST threshold (OpenCV ORB's ``fastThreshold``)."""
    edge_threshold: int = 19
    """Border in pixels where no feature is detected (ORB-SLAM uses 19)."""
    grid_cols: int = 16
    """Cells across the image for the even distribution."""
    grid_rows: int = 10
    """Cells down the image for the even distribution."""
    oversample: float = 2.0
    """Candidates detected per kept feature before the grid selection."""


@dataclass(frozen=True)
class LkConfig:
    """Pyramidal Lucas–Kanade and the checks after it (Algorithm 1)."""

    win_size: int = 9
    """LK window side in pixels (odd). Small because the IMU prediction starts LK close to the
    answer: the benchmark shows the same inliers as a 15 px window over 4 levels at 1/3 of
    the time (plain LK needs the larger window and pyramid)."""
    max_level: int = 2
    """Top level of the LK pyramid (OpenCV pyramids halve per level: 3 levels, 1/4 scale)."""
    fb_max_level: int = 1
    """Top pyramid level of the backward pass when a motion model predicts where it ends (the
    inverse IMU rotation); without one (plain LK) the backward pass uses ``max_level``."""
    max_iterations: int = 30
    """LK iterations per level at most."""
    epsilon: float = 0.01
    """LK stops when the update is below this many pixels."""
    fb_threshold_px: float = 1.0
    """Forward–backward check: tracks whose round trip misses by more are dropped."""
    check_forward_backward: bool = True
    """Run the backward LK pass and its check."""
    imu_residual_min_px: float = 20.0
    """IMU-consistency bound: a track is dropped when its offset from the IMU prediction exceeds
    ``max(imu_residual_min_px, imu_residual_factor × median offset)`` (the rest's parallax)."""
    imu_residual_factor: float = 6.0
    """See ``imu_residual_min_px``."""
    ransac: bool = True
    """Drop outliers with RANSAC on undistorted points."""
    ransac_model: RansacModel = RansacModel.FUNDAMENTAL
    """Model fitted by RANSAC (0.5 ms vs 3.4 ms for E with 1000 tracks, 20 % outliers)."""
    ransac_threshold_px: float = 1.0
    """RANSAC inlier threshold in pixels (converted to normalised units with the focal)."""
    ransac_confidence: float = 0.99
    """RANSAC confidence."""
    min_ransac_points: int = 8
    """Below this many tracks RANSAC is skipped."""


@dataclass(frozen=True)
class TopUpConfig:
    """New corners on non-keyframes where tracks are sparse (grid of cells)."""

    enabled: bool = True
    """Add corners on non-keyframes; they get new track ids and keyframe index -1."""
    cell_px: int = 48
    """Cell side in pixels; a cell with fewer than ``min_per_cell`` tracks gets new corners."""
    min_per_cell: int = 1
    """Tracks wanted per cell."""
    max_new_per_frame: int = 100
    """Cap of new corners per frame."""
    min_lost: int = 10
    """Top up once this many tracks were lost since the last top-up (or keyframe) ..."""
    max_interval_frames: int = 10
    """... or after this many frames without one (FAST on the whole image costs ~1 ms)."""
    fast_threshold: int = 20
    """FAST threshold of the new corners (the strongest corner of each sparse cell is kept)."""
    min_distance_px: int = 12
    """Minimum distance between a new corner and any tracked point."""


@dataclass(frozen=True)
class StaticBiasConfig:
    """Gyro bias before VI initialisation, learnt while the images show no motion.

    Before the edge sends its biases the gyro prediction would turn the raw bias into image
    motion (EuRoC's ADIS16448 reads ~4.6 °/s at rest, ~1.8 px per frame at 20 Hz). Frames
    whose tracked points moved less than ``max_median_flow_px`` (median) are taken as
    standstill and their mean gyro reading updates the bias (running mean); the bias is used
    once ``min_static_frames`` such frames were seen.
    """

    enabled: bool = True
    max_median_flow_px: float = 0.3
    """Median track displacement below which a frame counts as standstill."""
    min_static_frames: int = 5
    """Standstill frames needed before the learnt bias is applied."""
    min_tracks: int = 50
    """Tracks needed for the standstill test."""


@dataclass(frozen=True)
class KeyframeDecisionConfig:
    """Keyframe decision of the paper's Fig. 4.

    A frame becomes a keyframe when the tracks continuing the last keyframe's features fall
    below ``min_tracked`` or below ``min_tracked_fraction`` of that keyframe's features, or when
    more than ``max_interval_s`` have passed since it. ``min_interval_s`` holds the decision
    back right after a keyframe (except when tracking is lost: fewer than ``lost_tracked``).
    """

    min_tracked: int = 150
    """Absolute floor of tracked keyframe features."""
    min_tracked_fraction: float = 0.5
    """Floor of tracked features relative to the last keyframe's feature count."""
    max_interval_s: float = 1.0
    """Longest time between keyframes."""
    min_interval_s: float = 0.0
    """Shortest time between keyframes (unless tracking is lost)."""
    lost_tracked: int = 30
    """Below this many tracks a keyframe is taken regardless of ``min_interval_s`` ..."""
    lost_min_interval_s: float = 0.0
    """... once this long [s] has passed since the last keyframe (0: at once; an uplink
    budget sets the time the link needs to carry one keyframe, so that a stretch of lost
    tracking does not send a keyframe per frame: the tracker tops its tracks up with corners
    on the frames between, and the next keyframe follows when the link has room)."""
    every_frame: bool = False
    """Baseline: every frame is a keyframe (the paper's reference [55] intra mode)."""


@dataclass(frozen=True)
class FrontEndConfig:
    """Everything the robot's front end needs (one object, handed down)."""

    orb: OrbConfig = field(default_factory=OrbConfig)
    lk: LkConfig = field(default_factory=LkConfig)
    top_up: TopUpConfig = field(default_factory=TopUpConfig)
    keyframe: KeyframeDecisionConfig = field(default_factory=KeyframeDecisionConfig)
    static_bias: StaticBiasConfig = field(default_factory=StaticBiasConfig)
    prediction: PredictionMode = PredictionMode.IMU
    """Initial guess of LK (IMU-assisted or the plain-LK baseline)."""
    tracking: TrackingMode = TrackingMode.OPTICAL_FLOW
    """Optical flow (the paper) or ORB matching on every frame (baseline)."""
    quantisation_px: float = 0.25
    """Output keypoints lie on this grid; the tracker continues from the quantised values."""
    keyframe_association_radius_px: float = 3.0
    """A surviving track continues as the nearest keyframe ORB keypoint within this radius."""
    keyframe_prefers_tracks: bool = False
    """A keyframe's ORB selection keeps first, for each surviving track, the detected corner
    within ``keyframe_association_radius_px`` of it (so the track continues), then spreads
    the rest over the grid. False: the grid alone picks (ORB-SLAM's distribution). An uplink
    budget's keyframe plan turns it on: its keyframes are 1-2 s apart and ~300 features, and
    the grid alone continued ~1 track with a map point from one keyframe to the next."""
    carry_track_descriptors: bool = True
    """A keyframe feature that continues a track keeps the track's descriptor while its own
    ORB descriptor lies within ``carry_max_hamming`` bits of it, and the codec sends none for
    it (``CodecConfig.carry_track_descriptors``); otherwise it takes its own, coded against
    the track's. False: always its own (the paper's [55] inter mode)."""
    carry_max_hamming: int = 25
    """Half the matchers' acceptance (the edge's ``MappingConfig.match_max_hamming`` and the
    cloud's ``fuse_max_hamming``, 50 bits): by the triangle inequality whatever the feature's
    own descriptor matches within 25 bits, the carried one matches within 50, so a carried
    descriptor finds what the current view would (a track seen from far around keeps a stale
    one otherwise: the mixed-camera team merged less often)."""
    orb_match_max_hamming: int = 64
    """ORB-matching baseline: largest Hamming distance of an accepted match."""
    orb_match_ratio: float = 0.8
    """ORB-matching baseline: Lowe ratio between best and second-best distance."""
    imu_buffer_s: float = 2.0
    """IMU history kept for re-propagating late inertial states from the edge."""

"""Options of the cloud tier's domain code (paper Section VI.B), one frozen dataclass per block.

Every default is documented where it is declared; :class:`CloudConfig` bundles them so a
service builds one object and hands the parts down (the service's own options, which nest
this one, are in :mod:`services.cloud.service_config`).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field


class AlignmentMode(enum.Enum):
    """Degrees of freedom of the transform that aligns one map onto another.

    YAW_TRANSLATION: 4-DoF (rotation about gravity + translation), right for gravity-aligned
    visual-inertial maps. YAW_TRANSLATION_SCALE: 5-DoF, the same and a scale (how a map
    fragment merges, ``MergeConfig.fragment_max_scale_change``). SE3: full 6-DoF rigid. SIM3:
    7-DoF similarity (monocular maps).
    """

    YAW_TRANSLATION = "yaw_translation"
    YAW_TRANSLATION_SCALE = "yaw_translation_scale"
    SE3 = "se3"
    SIM3 = "sim3"


@dataclass(frozen=True)
class PlaceRecognitionConfig:
    """Place-recognition options (DBoW2 / ORB-SLAM loop detection).

    min_score_floor: lowest BoW L1 score a candidate may have, used alone when the query has
        no covisible keyframe yet (default 0.015).
    min_common_words_ratio: candidates must share at least this fraction of the best
        candidate's shared-word count (ORB-SLAM: 0.8).
    group_size: covisible keyframes per candidate whose scores are accumulated (ORB-SLAM: 10).
    group_score_ratio: groups scoring below this fraction of the best group are dropped
        (ORB-SLAM: 0.75).
    min_consistency: consecutive query keyframes of the same agent whose candidate groups
        must overlap before a candidate is accepted (ORB-SLAM: 3).
    recent_window_s: keyframes of the query's own agent within this many seconds of the
        query are never candidates (default 10 s).
    exclude_covisible: never return keyframes covisible with the query (default True).
    max_candidates: at most this many accepted candidates per query (default 3).
    early_candidates: besides those, up to this many of the best candidates that are not yet
        consistent over ``min_consistency`` queries are returned for verification now; they
        are accepted only when the query's covisible keyframes agree with the verified pose
        (``VerificationConfig.covisible_agree``), as ORB-SLAM3 does instead of waiting for
        the next keyframes (default 1; 0: consecutive queries only, ORB-SLAM2's rule).
    """

    min_score_floor: float = 0.015
    min_common_words_ratio: float = 0.8
    group_size: int = 10
    group_score_ratio: float = 0.75
    min_consistency: int = 3
    recent_window_s: float = 10.0
    exclude_covisible: bool = True
    max_candidates: int = 3
    early_candidates: int = 1


@dataclass(frozen=True)
class VerificationConfig:
    """Geometric verification options (strict: a false merge is never acceptable).

    max_hamming: largest descriptor distance of a match, bits (default 50, ORB-SLAM TH_LOW).
    ratio: best / second-best distance ratio test (default 0.75).
    group_level: words are matched within their vocabulary ancestor at this tree level
        (DBoW2 direct index); None matches within the same word only (default None).
    min_initial_matches: putative 3D–2D matches needed before RANSAC (default 20).
    reprojection_px: RANSAC / inlier reprojection threshold, pixels (default 4.0).
    min_inliers: inliers of the final 3D–2D pose required (default 30).
    min_inlier_ratio: inliers / putative matches of the initial RANSAC (default 0.4).
    projection_radius_px: search radius of the guided projection search that expands the
        matches with the candidate's covisible map points (default 8.0).
    covisible_expansion: covisible keyframes of the candidate whose map points are projected
        (default 10).
    max_tilt_deg: for gravity-aligned maps, the relative rotation between the two map frames
        must be a rotation about gravity up to this many degrees of roll/pitch; None turns the
        check off (default 5.0).
    min_3d3d_agreement: when the query keypoints have their own map points, this fraction of
        inlier pairs must agree in 3D after alignment (default 0.5).
    agreement_distance_m: 3D agreement distance, metres (default 0.25).
    covisible_checks: a candidate accepted before it was consistent over consecutive queries
        (``PlaceRecognitionConfig.early_candidates``) is checked in this many of the query's
        best covisible keyframes (ORB-SLAM3's covisibility consistency; default 5) ...
    covisible_agree: ... at least this many of which must agree (default 2; the query makes
        the third, as ORB-SLAM3's three) ...
    covisible_min_matches: ... each with this many keypoints within ``reprojection_px`` of the
        candidate group's map points projected at the keyframe's own pose (default 30).
    seed: RANSAC random seed (default 0; deterministic).
    """

    max_hamming: int = 50
    ratio: float = 0.75
    group_level: int | None = None
    min_initial_matches: int = 20
    reprojection_px: float = 4.0
    min_inliers: int = 30
    min_inlier_ratio: float = 0.4
    projection_radius_px: float = 8.0
    covisible_expansion: int = 10
    max_tilt_deg: float | None = 5.0
    min_3d3d_agreement: float = 0.5
    agreement_distance_m: float = 0.25
    covisible_checks: int = 5
    covisible_agree: int = 2
    covisible_min_matches: int = 30
    seed: int = 0


@dataclass(frozen=True)
class MergeConfig:
    """Map-merging options.

    mode: degrees of freedom of the map-to-map transform (default 4-DoF yaw + translation).
    min_3d_pairs: 3D–3D pairs needed to estimate the transform from points; with fewer the
        verified 6-DoF pose is projected onto ``mode`` (default 10).
    fuse_distance_m: duplicate map points closer than this after alignment are fused
        (default 0.05 m).
    fuse_max_hamming: ... and whose descriptors differ by at most this many bits (default 50).
    fuse_loop_points: a loop closed within one map fuses its verified 3D-3D point pairs too
        (default True; ``services/cloud/fusion/merge.py``): the full BA then links the two visits
        through shared points, not only through the loop's relative pose. On replays of seeds
        0 / 1 / 2, joint ATE 0.23 / 0.27 / 0.38 cm with it against 0.54 / 0.52 / 0.51 cm
        without (benchmarks/results/loop_recall.md).
    fragment_max_scale_change: a *fragment* (a map whose robots have all moved on to newer
        maps, e.g. the one an edge began after a tracking loss and left at the next) may
        differ in scale from the map it merges with by this fraction (default 0.2): its
        point pairs pass verification's 3D check after a yaw + translation + scale
        alignment, and the fragment merges into the other map with that scale. A robot's map
        takes no scale while the robot still uses it (its edge keeps sending that map's poses
        in its own scale). On a hover flight with exposure steps (seed 1), a map robot1 began
        after a tracking loss agreed with the others at 0.875 of their scale within 1 cm, but
        0-29 % of its point pairs within 0.25 m rigidly, and never merged back. 0: rigid only.
    """

    mode: AlignmentMode = AlignmentMode.YAW_TRANSLATION
    min_3d_pairs: int = 10
    fuse_distance_m: float = 0.05
    fuse_max_hamming: int = 50
    fuse_loop_points: bool = True
    fragment_max_scale_change: float = 0.2

    def __post_init__(self) -> None:
        if not 0 <= self.fragment_max_scale_change < 1:
            raise ValueError(
                f"fragment_max_scale_change must be in [0, 1), got {self.fragment_max_scale_change}"
            )


@dataclass(frozen=True)
class GlobalOptimizationConfig:
    """Pose-graph options (paper Eq. 20, pose-graph stage).

    odometry_sigma_rot_rad / odometry_sigma_trans_m: standard deviation of a relative pose
        between consecutive keyframes of one agent at the reference covisibility weight
        (defaults 0.01 rad, 0.02 m).
    reference_weight: covisibility weight (shared map points) at which the odometry sigmas
        apply; information scales linearly with weight, clamped to [0.25, 4] (default 50).
    covisibility_min_weight: extra relative-pose edges between keyframes sharing at least this
        many map points (ORB-SLAM essential graph: 100). Measured from the current estimates
        they make the graph stiff enough to resist loop corrections, so default 0 (off).
    loop_sigma_rot_rad / loop_sigma_trans_m: loop / merge constraint sigmas (defaults 0.02 rad,
        0.05 m).
    loop_robust_kernel: "cauchy", "huber" or "none" (default "cauchy").
    loop_kernel_scale: kernel scale on the whitened error (default 10: a loop that closes
        half a metre of drift must still pull; gross outliers are removed afterwards).
    loop_outlier_whitened: loop edges whose whitened error exceeds this after the robust
        solve are dropped and the graph is solved again (default 5.0).
    prior_sigma: sigma of the prior on the first keyframe (default 1e-6).
    max_iterations: Levenberg–Marquardt iterations (default 100).
    attitude_sigma_rad: each keyframe's roll and pitch (the direction of gravity in its body
        frame, which the edge's visual-inertial odometry observes through the IMU and the
        atlas holds from the edge's latest pose) held with this sigma (default 0.002 rad,
        0.11°; 0: off), as VINS-Mono's and COVINS' 4-DoF pose graphs do. Without it, loop
        corrections tilted the edges' gravity-aligned maps by 0.3° (median, up to 1°) and the
        VIO's IMU terms then fought the tilted map. (The full BA has its own setting,
        ``FullBAConfig.attitude_sigma_rad``, off by default.)
    """

    odometry_sigma_rot_rad: float = 0.01
    odometry_sigma_trans_m: float = 0.02
    reference_weight: float = 50.0
    covisibility_min_weight: int = 0
    loop_sigma_rot_rad: float = 0.02
    loop_sigma_trans_m: float = 0.05
    loop_robust_kernel: str = "cauchy"
    loop_kernel_scale: float = 10.0
    loop_outlier_whitened: float = 5.0
    prior_sigma: float = 1e-6
    max_iterations: int = 100
    attitude_sigma_rad: float = 0.002


@dataclass(frozen=True)
class FullBAConfig:
    """Full bundle-adjustment options (paper Eq. 20, full stage;
    ``services/cloud/optimization/full_ba.py``).

    enabled: run the full stage at all (default True; ``recslam cloud --no-full-ba``).
    pixel_sigma: reprojection standard deviation at pyramid level 0, pixels (default 1.0) ...
    level_scale: ... times this per level (ORB's scale factor, default 1.2).
    robust_kernel: "huber", "cauchy" or "none" on the reprojection terms (default "huber").
    kernel_scale: kernel threshold on the whitened error (default 2.447 = sqrt(5.991), the
        95 % chi-square bound with 2 DoF, as ORB-SLAM).
    max_initial_reprojection_px: observations reprojecting worse than this at the start are
        left out (default 20 px).
    min_depth_m: observations with a point closer than this in front of the camera at the
        start are left out (default 0.05 m).
    odometry_sigma_rot_rad / odometry_sigma_trans_m: sigmas of the relative-pose constraint
        between consecutive keyframes of one agent, the stand-in of the IMU term (defaults
        0.1 rad, 0.2 m). Its measurement is the current estimate, drift included, so it is
        only a weak regulariser (keeps sparsely observed keyframes attached): on the
        recorded 3-robot run, one full BA of the final map took joint ATE from 5.5 cm to
        4.4 / 2.6 / 1.4 / 1.2 cm with 0.01 / 0.05 / 0.1 / 0.3 rad and 0.02 / 0.1 / 0.2 / 0.6 m
        (benchmarks/results/cloud_full_ba.md).
    max_iterations: Levenberg–Marquardt iterations (default 15).
    relative_error_tol: stop when the error decreases by less than this fraction (1e-4).
    max_seconds: stop after the iteration that crosses this wall time, graph construction
        included (default 60 s).
    attitude_sigma_rad: hold each keyframe's roll and pitch with this sigma as the pose graph
        does (``GlobalOptimizationConfig.attitude_sigma_rad``); default 0: off. Replayed on a
        recorded run (modelled schedule), joint ATE 1.72 cm without attitude factors, 1.58 cm
        with them in the pose graph only, 1.94 cm in the pose graph and the full BA at 0.002
        rad: the images fix a keyframe's tilt relative to the map better than the VIO's
        gravity (its tilt errors: median 0.04-0.08 deg, p95 0.22-0.39 deg).
    imu_factors: visual-inertial global BA (``services/cloud/optimization/inertial.py``): between
        consecutive keyframes of one agent with forwarded IMU, a preintegrated
        ``CombinedImuFactor`` over pose, velocity and bias states replaces the relative-pose
        term (default True: on the recordings of seeds 0, 1, 2 replayed with the live
        schedule, joint ATE 1.60 / 2.03 / 1.35 cm without, 0.98 / 1.48 / 1.06 cm with, scale
        error +0.57 / -0.85 / +0.14 % -> -0.06 / -0.01 / +0.16 %; see
        benchmarks/results/cloud_vi_ba.md).
    gravity_mps2: gravity along the map's -z (default 9.81, the edge VIO's).
    imu_integration_sigma: preintegration integration noise (default 1e-4, the edge's).
    imu_noise_scale: the robot's IMU noise densities and random walks are multiplied by this
        in the IMU factors (default 3). Chosen on the seed-0 recording, final map, one VI full
        BA: joint ATE 1.66 / 0.96 / 1.01 / 2.63 cm with 1 / 3 / 10 / 0.5 (1.60 cm without IMU
        factors); the nominal densities over-trust the preintegration against the images.
    imu_noise_from_data / imu_noise_window_samples: the densities are first raised to the white
        noise the agent's newest samples show where it exceeds them 1.5-fold
        (``common.imu.with_measured_noise``, as the edge's VIO does): a real MAV's vibration is
        25-60x the ADIS16448's datasheet; a simulated IMU keeps its calibration.
    imu_reweight_rounds: after the solve, re-weight the IMU to fit and solve again, at most this
        many times (default 3; 0: the noise above as it is). Variance component estimation
        (Förstner 1979): the IMU factors' whitened squared residuals over their redundancy
        (:func:`services.cloud.optimization.inertial.imu_variance_factor`) scale the noise by
        its square root. The second-difference measurement above sees a MAV's rotor vibration,
        which mostly cancels over a keyframe interval: on EuRoC V2_01-03's recorded IMUs along
        their rendered flights, the preintegrated velocity errs by 0.04 m/s²/√Hz over 0.25-0.5 s
        against 0.11 measured (x3: 0.33), so the IMU held the map's scale only to ±3.4 % and the
        scale stayed where the young maps' merges and loops put it (−0.4 to −0.8 %). The fit
        settles near x0.3 of the measured density (0.033, the error measured against the
        ground truth), and the same final full BA ends at −0.21 % instead of −0.54 % (joint
        1.34 -> 0.69 cm); live runs 1.44 -> 0.86 cm, 15 ms offset 3.63 -> 1.15 cm
        (benchmarks/results/map_scale.md). The rounds stay within ``max_seconds`` (at shutdown
        ``full_ba_at_shutdown_s``): on a loaded machine they may not all run ...
    imu_reweight_tolerance: ... stopping when the scale changes by less than this fraction
        (default 0.1) ...
    imu_reweight_max_step: ... each round changing it by at most this factor either way
        (default 10) ...
    imu_noise_scale_min / imu_noise_scale_max: ... and keeping it within these (defaults 0.25,
        10: a fit cannot make the IMU four times more certain than its calibration or the
        measured noise, nor ten times less).
    imu_max_interval_s: keyframe intervals longer than this get no IMU factor (default 3 s) ...
    imu_max_gap_s: ... nor do intervals with two IMU samples further apart (default 0.05 s).
    bias_prior_accel / bias_prior_gyro: sigmas of the prior on the first bias of each agent's
        chain, at the edge's estimate (defaults 0.1 m/s², 0.01 rad/s).
    gauge_tilt_sigma_rad: with IMU factors in the solve (and no prior-map keyframes held), the
        prior that fixes the map at its first keyframe holds its roll and pitch only with this
        sigma (0: held like the rest, the default), so gravity through the IMU factors sets the
        map's tilt: the 4-DoF gauge of visual-inertial estimation (position and yaw). Held,
        the first keyframe keeps the tilt the edge's early gravity estimate gave it (0.01-0.2°
        on the recordings): with a noise-free IMU weighted 10x (a seed-2 final map) the
        solve then ends 0.41 cm off at scale 0.998, freed 0.18 cm. Not the default:
        on replays of 12 recordings (seeds 0-2, with and without MBP) 0.05 rad was worse on
        8, +10 % joint ATE in all, and mixed on the harder flights (inward seed 0 5.06 ->
        4.83 cm, hover seed 1 0.36 -> 0.40 cm).
    incremental: solve on the map's iSAM2 graph, updated with what changed since the last
        full BA (``services/cloud/optimization/incremental_ba.py``; a batch solve builds it
        first and after merges); default True (False: the batch solve every time, whose cost grows
        with the map: 14-36 s at 5k keyframes against under 1 s per update,
        ``cloud_vi_ba_incremental.md``) ...
    incremental_min_keyframes: ... for maps of at least this many keyframes; smaller ones
        are solved in batch (default 500: on two 3-robot recordings of ~125 keyframes the
        iSAM2 updates took 1.3 / 3.8 s median against 1.8 / 1.8 s batch, same ATE; at 1k
        keyframes an update costs a tenth of a batch solve).
    incremental_max_updates: iSAM2 updates (relinearisation steps) per full BA, at most
        (default 4: the service's full BA comes after tens of new keyframes, and one update
        leaves such a step short of the batch solution; ``benchmarks/bench_cloud_vi_ba.py``
        times 1 and 4) ...
    relinearize_threshold: ... relinearising variables whose update exceeds this (0.01).
    relinearize_skip: ... checking for relinearisation every this many updates (1).
    relinearize_budget: ... at most this many variables per update, those with the largest
        pending step first (0: no bound) ...
    partial_relinearization_check: ... looking for them from the Bayes tree's root down,
        into a clique's children only while the clique has a variable past the threshold
        (iSAM2's partial check; default True): with the full check, updates on a
        5k-keyframe map relinearised 1k-10k old points that had moved by a centimetre and
        took up to 5-9 s; with it, under 1 s (``cloud_vi_ba_incremental.md``).
    point_prior_sigma_m: in the iSAM2 graph, a weak prior on every point at its start
        position keeps a point that lost observations solvable (default 10 m).
    """

    enabled: bool = True
    pixel_sigma: float = 1.0
    level_scale: float = 1.2
    robust_kernel: str = "huber"
    kernel_scale: float = 2.447
    max_initial_reprojection_px: float = 20.0
    min_depth_m: float = 0.05
    odometry_sigma_rot_rad: float = 0.1
    odometry_sigma_trans_m: float = 0.2
    max_iterations: int = 15
    relative_error_tol: float = 1e-4
    max_seconds: float = 60.0
    attitude_sigma_rad: float = 0.0
    imu_factors: bool = True
    gravity_mps2: float = 9.81
    imu_integration_sigma: float = 1e-4
    imu_noise_scale: float = 3.0
    imu_noise_from_data: bool = True
    imu_noise_window_samples: int = 4000
    imu_reweight_rounds: int = 3
    imu_reweight_tolerance: float = 0.1
    imu_reweight_max_step: float = 10.0
    imu_noise_scale_min: float = 0.25
    imu_noise_scale_max: float = 10.0
    imu_max_interval_s: float = 3.0
    imu_max_gap_s: float = 0.05
    bias_prior_accel: float = 0.1
    bias_prior_gyro: float = 0.01
    gauge_tilt_sigma_rad: float = 0.0
    incremental: bool = True
    incremental_min_keyframes: int = 500
    incremental_max_updates: int = 4
    relinearize_threshold: float = 0.01
    relinearize_skip: int = 1
    relinearize_budget: int = 0
    partial_relinearization_check: bool = True
    point_prior_sigma_m: float = 10.0


@dataclass(frozen=True)
class MbpConfig:
    """Map backbone profiling options.

    enabled: run MBP at all (default True).
    min_shared: a removed keyframe's absorber shares at least this many map points with it,
        and the kept keyframes stay connected through covisibility edges of at least this
        weight (default 50, the pose graph's ``reference_weight``, at which it trusts a
        relative pose at nominal strength; chosen by measurement: on the recorded 3-robot run
        (benchmarks/results/table3.md) 15 removed 48 % of the keyframes with joint ATE
        2.46 -> 3.23 cm, 50 removed 43 % with 2.46 -> 2.92 cm).
    cover_ratio: a keyframe is removed only while the kept keyframes together observe at
        least this fraction of its map points (default 0.5; keyframes reach the cloud
        sparsely: on that run consecutive ones share a median 43 % of their points, all
        others together see a median 73 %; with min_shared 15, 0.6 removed 46 % with joint
        ATE 3.17 cm).
    max_virtual_reprojection_px: an observation of a removed keyframe is "good" (and folded
        into the absorbing keyframe) if it reprojects within this many pixels (default 3.0).
    min_observations: map points left with fewer observations are removed (default 2; at
        least 1: a map point needs an observer).
    blend_retired: a removed keyframe's pose follows both kept keyframes around it in time,
        blended by time, not only the one its loops moved to (default True;
        ``services.cloud.atlas.retired.retired_pose``).
    max_interval_s: a keyframe stays when removing it would leave its agent's kept
        keyframes around it further apart in time than this, seconds (default None: no limit;
        a pass while running has ``MbpScheduleConfig.running``'s 1.5 s).
    """

    enabled: bool = True
    min_shared: int = 50
    cover_ratio: float = 0.5
    max_virtual_reprojection_px: float = 3.0
    min_observations: int = 2
    blend_retired: bool = True
    max_interval_s: float | None = None

    def __post_init__(self) -> None:
        if self.min_observations < 1:
            raise ValueError(f"min_observations must be >= 1, got {self.min_observations}")


@dataclass(frozen=True)
class CloudConfig:
    """All cloud domain options (built once by the service, handed down)."""

    place_recognition: PlaceRecognitionConfig = field(default_factory=PlaceRecognitionConfig)
    verification: VerificationConfig = field(default_factory=VerificationConfig)
    merge: MergeConfig = field(default_factory=MergeConfig)
    optimization: GlobalOptimizationConfig = field(default_factory=GlobalOptimizationConfig)
    full_ba: FullBAConfig = field(default_factory=FullBAConfig)
    mbp: MbpConfig = field(default_factory=MbpConfig)

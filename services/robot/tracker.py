"""IMU-assisted pyramidal LK tracking with ORB keyframes: the robot's front end (Algorithm 1).

The stateful :class:`FrontEnd` over the stateless steps of :mod:`services.robot.optical_flow`.
Per frame: every track's position in the new frame is predicted from the IMU
(:mod:`services.robot.imu_prediction`); LK refines the prediction
(``OPTFLOW_USE_INITIAL_FLOW``); a backward LK pass checks the round trip; tracks whose offset
from the IMU prediction is far larger than the rest's are dropped; RANSAC (fundamental or
essential matrix on undistorted points) removes the remaining outliers. The keyframe decision
(Fig. 4) then either keeps the frame as a non-keyframe (sparse cells get new FAST corners)
or makes it a keyframe: ORB is extracted and the track set is re-seeded from the ORB
keypoints, surviving tracks handing their identity to the nearest ORB keypoint.

Output contract (:class:`TrackedFrame`), relied on by the feature codec:

- non-keyframe: rows are the previous frame's tracks that survived, in their previous order
  (``survived_mask_vs_previous`` selects them), followed by new top-up corners
  (``keyframe_feature_index == -1``);
- keyframe: rows are the keyframe's ORB features in extraction order
  (``keyframe_feature_index == arange(N)``); ``survived_mask_vs_previous`` marks previous tracks
  whose identity continues in one of them;
- keypoints are level-0 distorted pixels on the ``quantisation_px`` grid, and the next frame
  is tracked from exactly these values.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np

from common.calibration import CameraCalibration, ImuCalibration
from common.errors import RecslamError
from common.vocabulary import hamming_rows
from services.robot.config import FrontEndConfig, PredictionMode, TrackingMode
from services.robot.imu_prediction import InertialState, MotionPredictor, predict_rotation
from services.robot.keyframe_decision import KeyframeReason, decide_keyframe
from services.robot.optical_flow import (
    BackPrediction,
    associate_nearest,
    quantise,
    ransac_inliers,
    top_up_corners,
    track_points,
)
from services.robot.orb_extractor import OrbExtractor, OrbFeatures
from services.robot.uplink_budget import KeyframePlan

logger = logging.getLogger(__name__)


class FrontEndError(RecslamError):
    """Invalid input to the robot's front end (image, timestamp, IMU)."""


class ImuSamples(Protocol):
    """IMU samples since the previous frame (e.g. ``common.data.euroc.ImuBatch``):
    ``timestamps_ns`` (K,) int64, ``gyro`` (K, 3) rad/s, ``accel`` (K, 3) m/s², IMU frame.
    Read-only members, so that frozen dataclasses match."""

    @property
    def timestamps_ns(self) -> np.ndarray: ...
    @property
    def gyro(self) -> np.ndarray: ...
    @property
    def accel(self) -> np.ndarray: ...


@dataclass(frozen=True)
class TrackingStats:
    """What happened to the tracks of one frame (counts) and how long it took (seconds)."""

    n_previous: int = 0
    """Tracks handed in from the previous frame."""
    n_predicted: int = 0
    """Of those, predicted by the IMU (0 for plain LK)."""
    n_predicted_3d: int = 0
    """Of those, predicted by reprojecting an edge 3D point."""
    n_lk: int = 0
    """LK converged inside the image."""
    n_fb: int = 0
    """Also passed the forward–backward check."""
    n_imu_consistent: int = 0
    """Also consistent with the IMU prediction."""
    n_inliers: int = 0
    """Also RANSAC inliers: the tracks that survive."""
    n_tracked_keyframe: int = 0
    """Survivors continuing a feature of the last keyframe (the keyframe decision's count)."""
    n_new: int = 0
    """Top-up corners added (non-keyframe) or ORB features without a track (keyframe)."""
    n_features: int = 0
    """Rows of the output."""
    prediction: str = "none"
    """``"gyro"``, ``"preintegration"`` or ``"none"``."""
    lk_time_s: float = 0.0
    """LK forward and backward passes (or descriptor matching in the ORB baseline)."""
    ransac_time_s: float = 0.0
    orb_time_s: float = 0.0
    total_time_s: float = 0.0
    """Whole ``process`` call, pyramid included."""


@dataclass(frozen=True, eq=False)
class TrackedFrame:
    """The front end's output for one frame (see the module docstring for the row order).

    ``track_ids`` (N,) int64 persistent identities; ``keyframe_feature_index`` (N,) int32, the
    index of the feature of keyframe ``keyframe_id`` each track continues (-1: born after it);
    ``keypoints`` (N, 2) float64 [px, level 0, quantised]; ``levels`` (N,) uint8 pyramid
    level σ of the originating keypoint; ``survived_mask_vs_previous`` (M,) bool over the
    previous frame's rows; ``descriptors`` (N, 32) uint8 and ``angles`` (N,) float32 [deg]
    on keyframes (and on every frame of the ORB-matching baseline), else None.
    """

    frame_index: int
    timestamp_ns: int
    is_keyframe: bool
    keyframe_reason: KeyframeReason
    keyframe_id: int
    track_ids: np.ndarray
    keyframe_feature_index: np.ndarray
    keypoints: np.ndarray
    levels: np.ndarray
    survived_mask_vs_previous: np.ndarray
    descriptors: np.ndarray | None
    angles: np.ndarray | None
    stats: TrackingStats

    def __len__(self) -> int:
        return len(self.track_ids)


class FrontEnd:
    """The robot's front end: ``process`` one frame at a time, ``set_inertial_state`` when the
    edge sends its estimate. Sans-I/O: no sockets, no clocks except for the timing stats."""

    def __init__(
        self, config: FrontEndConfig, camera: CameraCalibration, imu: ImuCalibration
    ) -> None:
        self.config = config
        self.base_config = config  # (set_keyframe_plan works from it)
        self.camera = camera
        self.predictor = MotionPredictor(
            camera, imu, config.imu_buffer_s, config.static_bias.min_static_frames
        )
        self.orb = OrbExtractor(config.orb)
        self._fast = cv2.FastFeatureDetector.create(threshold=config.top_up.fast_threshold)
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        self._frame_index = -1
        self._prev_t: int | None = None
        self._prev_image: np.ndarray | None = None
        self._ids = np.zeros(0, np.int64)
        self._kf_index = np.zeros(0, np.int32)
        self._pts = np.zeros((0, 2))
        self._levels = np.zeros(0, np.uint8)
        self._desc: np.ndarray | None = None
        self._next_id = 0
        self._kf_id = -1
        self._kf_t: int | None = None
        self._kf_n: int | None = None
        self._lost_since_top_up = 0
        self._frames_since_top_up = 0
        logger.info("front end options: %s", config)

    @property
    def vi_initialised(self) -> bool:
        """True once the edge's inertial state has been applied."""
        return self.predictor.initialised

    def set_inertial_state(
        self,
        state: InertialState,
        track_ids: np.ndarray | None = None,
        p_world: np.ndarray | None = None,
    ) -> None:
        """Apply the edge's inertial estimate (and 3D points (M, 3) of tracks (M,), if any)."""
        self.predictor.set_inertial_state(state, track_ids, p_world)

    def set_time_offset(self, offset_ns: int) -> None:
        """The camera-IMU time offset the edge estimated (``t_imu = t_cam + offset``, ns)."""
        self.predictor.set_time_offset(offset_ns)

    def update_landmarks(
        self,
        track_ids: np.ndarray,
        p_world: np.ndarray,
        *,
        replace: bool = False,
        forget: np.ndarray | None = None,
        active: np.ndarray | None = None,
    ) -> None:
        """Edge 3D points (M, 3) [m, world] of tracks (M,): see
        :meth:`MotionPredictor.update_landmarks`."""
        self.predictor.update_landmarks(
            track_ids, p_world, replace=replace, forget=forget, active=active
        )

    def _new_ids(self, n: int) -> np.ndarray:
        ids = np.arange(self._next_id, self._next_id + n, dtype=np.int64)
        self._next_id += n
        return ids

    def _check_input(self, image: np.ndarray, timestamp_ns: int) -> None:
        cam = self.camera
        if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 2:
            raise FrontEndError(
                f"frame at {timestamp_ns} ns: need a uint8 (H, W) grayscale image, got "
                f"{getattr(image, 'dtype', type(image))} {getattr(image, 'shape', '')}"
            )
        if image.shape != (cam.height, cam.width):
            raise FrontEndError(
                f"frame at {timestamp_ns} ns: image is {image.shape[1]}x{image.shape[0]}, "
                f"calibration says {cam.width}x{cam.height}"
            )
        if self._prev_t is not None and timestamp_ns <= self._prev_t:
            raise FrontEndError(
                f"frame timestamps must increase: {timestamp_ns} ns after {self._prev_t} ns"
            )

    def set_keyframe_plan(self, plan: KeyframePlan | None) -> None:
        """Keyframes within an uplink budget (:mod:`services.robot.uplink_budget`): at most
        ``plan.n_features`` ORB features, at least ``plan.min_interval_s`` apart (unless
        tracking is lost; then at least ``plan.lost_min_interval_s``), at most twice that;
        the tracked floor scales with the features; the keyframe's corners continue the
        tracks first (``keyframe_prefers_tracks``).
        None: the configured rules again."""
        base = self.base_config
        if plan is None:
            self.config = base
        else:
            n = min(base.orb.n_features, plan.n_features)
            kf = base.keyframe
            min_s = max(kf.min_interval_s, plan.min_interval_s)
            keyframe = dataclasses.replace(
                kf,
                min_interval_s=min_s,
                max_interval_s=max(kf.max_interval_s, 2.0 * min_s),
                lost_min_interval_s=max(kf.lost_min_interval_s, plan.lost_min_interval_s),
                min_tracked=min(kf.min_tracked, round(kf.min_tracked * n / base.orb.n_features)),
            )
            self.config = dataclasses.replace(
                base,
                orb=dataclasses.replace(base.orb, n_features=n),
                keyframe=keyframe,
                keyframe_prefers_tracks=True,
            )
        self.orb.n_features = self.config.orb.n_features

    def process(
        self, image: np.ndarray, timestamp_ns: int, imu: ImuSamples | None = None
    ) -> TrackedFrame:
        """Track one frame. ``imu``: samples since the previous frame (IMU frame)."""
        t_start = time.perf_counter()
        timestamp_ns = int(timestamp_ns)
        self._check_input(image, timestamp_ns)
        if imu is not None and len(imu.timestamps_ns):
            self.predictor.add_imu(imu.timestamps_ns, imu.gyro, imu.accel)
        self._frame_index += 1
        if self.config.tracking is TrackingMode.ORB_MATCHING:
            frame = self._process_orb_matching(image, timestamp_ns, t_start)
        else:
            frame = self._process_optical_flow(image, timestamp_ns, t_start)
        self._prev_t = timestamp_ns
        return frame

    # ------------------------------------------------------------------ optical flow (paper)

    def _process_optical_flow(
        self, image: np.ndarray, timestamp_ns: int, t_start: float
    ) -> TrackedFrame:
        cfg = self.config
        n_prev = len(self._ids)
        stats: dict[str, object] = {"n_previous": n_prev}
        survived = np.zeros(n_prev, dtype=bool)
        cur_pts = np.zeros((0, 2))
        if self._prev_image is not None and n_prev:
            guess, source, n_3d, back = self._predict(timestamp_ns)
            res = track_points(
                cfg.lk,
                self.camera,
                self._prev_image,
                image,
                self._pts,
                guess,
                source != "none",
                back,
            )
            survived = res.keep
            cur_pts = quantise(res.cur_pts[survived], cfg.quantisation_px)
            self._learn_static_bias(self._pts[survived], cur_pts, timestamp_ns)
            stats.update(
                n_predicted=0 if source == "none" else n_prev,
                n_predicted_3d=n_3d,
                n_lk=res.n_lk,
                n_fb=res.n_fb,
                n_imu_consistent=res.n_imu_consistent,
                n_inliers=res.n_inliers,
                prediction=source,
                lk_time_s=res.lk_time_s,
                ransac_time_s=res.ransac_time_s,
            )
        self._prev_image = image
        ids = self._ids[survived]
        kf_index = self._kf_index[survived]
        levels = self._levels[survived]
        n_tracked_kf = int(np.count_nonzero(kf_index >= 0))
        dt_kf = None if self._kf_t is None else (timestamp_ns - self._kf_t) * 1e-9
        decision = decide_keyframe(cfg.keyframe, n_tracked_kf, self._kf_n, dt_kf)
        stats["n_tracked_keyframe"] = n_tracked_kf
        if decision.is_keyframe:
            t_orb = time.perf_counter()
            prefer = cur_pts if cfg.keyframe_prefers_tracks else None
            radius = cfg.keyframe_association_radius_px
            feats = self.orb.extract(image, prefer_px=prefer, prefer_radius_px=radius)
            stats["orb_time_s"] = time.perf_counter() - t_orb
            return self._make_keyframe(
                timestamp_ns, decision.reason, feats, cur_pts, ids, survived, stats, t_start
            )
        new_pts = np.zeros((0, 2))
        self._lost_since_top_up += n_prev - len(cur_pts)
        self._frames_since_top_up += 1
        if cfg.top_up.enabled and (
            self._lost_since_top_up >= cfg.top_up.min_lost
            or self._frames_since_top_up >= cfg.top_up.max_interval_frames
        ):
            new_pts = quantise(top_up_corners(image, cur_pts, cfg, self._fast), cfg.quantisation_px)
            self._lost_since_top_up = self._frames_since_top_up = 0
        n_new = len(new_pts)
        self._ids = np.concatenate([ids, self._new_ids(n_new)])
        self._kf_index = np.concatenate([kf_index, np.full(n_new, -1, np.int32)])
        self._pts = np.concatenate([cur_pts, new_pts])
        self._levels = np.concatenate([levels, np.zeros(n_new, np.uint8)])
        stats.update(n_new=n_new, n_features=len(self._ids))
        return self._emit(
            timestamp_ns, False, decision.reason, survived, None, None, stats, t_start
        )

    def _learn_static_bias(self, prev: np.ndarray, cur: np.ndarray, timestamp_ns: int) -> None:
        """Feed standstill frames (median track motion below the bound) to the gyro bias."""
        cfg = self.config.static_bias
        if not cfg.enabled or self.vi_initialised or len(cur) < cfg.min_tracks:
            return
        if len(self.predictor.buffer) == 0 or self._prev_t is None:
            return
        flow = float(np.median(np.linalg.norm(cur - prev, axis=1)))
        if flow < cfg.max_median_flow_px:
            td = self.predictor.time_offset_ns
            self.predictor.static_bias.add_standstill(
                self.predictor.buffer, self._prev_t + td, timestamp_ns + td
            )

    def _predict(self, timestamp_ns: int) -> tuple[np.ndarray, str, int, BackPrediction | None]:
        """Initial LK guess (N, 2) for the current tracks, its source, how many came from 3D
        points, and the backward motion model for the forward–backward check."""
        assert self._prev_t is not None
        if self.config.prediction is PredictionMode.NONE or len(self.predictor.buffer) == 0:
            return self._pts.copy(), "none", 0, None
        motion = self.predictor.predict_motion(self._prev_t, timestamp_ns)
        guess, by_point = self.predictor.predict_points(motion, self._pts, self._ids)
        R_prev_cur = motion.R_cur_prev.T
        shift = guess - self._pts
        camera = self.camera

        def back(cur: np.ndarray, rows: np.ndarray) -> np.ndarray:
            out = predict_rotation(camera, cur, R_prev_cur)
            from_point = by_point[rows]
            out[from_point] = cur[from_point] - shift[rows[from_point]]
            return out

        return guess, motion.source, int(by_point.sum()), back

    def _make_keyframe(
        self,
        timestamp_ns: int,
        reason: KeyframeReason,
        feats: OrbFeatures,
        cur_pts: np.ndarray,
        cur_ids: np.ndarray,
        survived: np.ndarray,
        stats: dict[str, object],
        t_start: float,
    ) -> TrackedFrame:
        """Re-seed the track set from the keyframe's ORB features; surviving tracks hand their
        identity to the nearest ORB keypoint within ``keyframe_association_radius_px``."""
        n = len(feats)
        kps = quantise(feats.keypoints, self.config.quantisation_px)
        ids = np.full(n, -1, np.int64)
        ia, ib = associate_nearest(cur_pts, kps, self.config.keyframe_association_radius_px)
        ids[ib] = cur_ids[ia]
        desc = feats.descriptors
        if self.config.carry_track_descriptors and self._desc is not None and len(ia):
            # A continued track keeps its descriptor (that of the last keyframe's feature it
            # continues) while the new ORB descriptor is close to it; tracks born since, by
            # top-up, take the new one.
            row = self._kf_index[survived][ia]
            had = np.flatnonzero(row >= 0)
            old = self._desc[row[had]]
            keep = hamming_rows(old, desc[ib[had]]) <= self.config.carry_max_hamming
            desc = desc.copy()
            desc[ib[had[keep]]] = old[keep]
        fresh = ids < 0
        ids[fresh] = self._new_ids(int(fresh.sum()))
        prev_rows = np.flatnonzero(survived)
        survived_kf = np.zeros_like(survived)
        survived_kf[prev_rows[ia]] = True
        self._kf_id += 1
        self._kf_t = timestamp_ns
        self._kf_n = n
        self._lost_since_top_up = self._frames_since_top_up = 0
        self._ids = ids
        self._kf_index = np.arange(n, dtype=np.int32)
        self._pts = kps
        self._levels = feats.levels.copy()
        self._desc = desc
        stats.update(n_new=int(fresh.sum()), n_features=n)
        return self._emit(
            timestamp_ns, True, reason, survived_kf, desc, feats.angles, stats, t_start
        )

    def _emit(
        self,
        timestamp_ns: int,
        is_keyframe: bool,
        reason: KeyframeReason,
        survived: np.ndarray,
        descriptors: np.ndarray | None,
        angles: np.ndarray | None,
        stats: dict[str, object],
        t_start: float,
    ) -> TrackedFrame:
        stats["total_time_s"] = time.perf_counter() - t_start
        arrays: list[np.ndarray] = [self._ids, self._kf_index, self._pts, self._levels, survived]
        out = [a.copy() for a in arrays]
        for a in out:
            a.setflags(write=False)
        return TrackedFrame(
            frame_index=self._frame_index,
            timestamp_ns=timestamp_ns,
            is_keyframe=is_keyframe,
            keyframe_reason=reason,
            keyframe_id=self._kf_id,
            track_ids=out[0],
            keyframe_feature_index=out[1],
            keypoints=out[2],
            levels=out[3],
            survived_mask_vs_previous=out[4],
            descriptors=descriptors,
            angles=angles,
            stats=TrackingStats(**stats),  # type: ignore[arg-type]
        )

    # ------------------------------------------------------------------ ORB-matching baseline

    def _process_orb_matching(
        self, image: np.ndarray, timestamp_ns: int, t_start: float
    ) -> TrackedFrame:
        cfg = self.config
        t_orb = time.perf_counter()
        feats = self.orb.extract(image)
        stats: dict[str, object] = {
            "n_previous": len(self._ids),
            "orb_time_s": time.perf_counter() - t_orb,
        }
        n = len(feats)
        kps = quantise(feats.keypoints, cfg.quantisation_px)
        ids = np.full(n, -1, np.int64)
        kf_index = np.full(n, -1, np.int32)
        survived = np.zeros(len(self._ids), dtype=bool)
        if self._desc is not None and len(self._desc) >= 2 and n >= 2:
            t0 = time.perf_counter()
            knn = self._matcher.knnMatch(feats.descriptors, self._desc, k=2)
            cur_i, prev_i = [], []
            for m in knn:
                if (
                    len(m) == 2
                    and m[0].distance <= cfg.orb_match_max_hamming
                    and m[0].distance < cfg.orb_match_ratio * m[1].distance
                ):
                    cur_i.append(m[0].queryIdx)
                    prev_i.append(m[0].trainIdx)
            ci, pi = np.array(cur_i, np.int64), np.array(prev_i, np.int64)
            _, first = np.unique(pi, return_index=True)  # one current feature per previous one
            ci, pi = ci[first], pi[first]
            stats["lk_time_s"] = time.perf_counter() - t0
            stats["n_lk"] = stats["n_fb"] = stats["n_imu_consistent"] = len(ci)
            t1 = time.perf_counter()
            inl = ransac_inliers(self.camera, self._pts[pi], kps[ci], cfg.lk)
            stats["ransac_time_s"] = time.perf_counter() - t1
            ci, pi = ci[inl], pi[inl]
            stats["n_inliers"] = len(ci)
            ids[ci] = self._ids[pi]
            kf_index[ci] = self._kf_index[pi]
            survived[pi] = True
        n_tracked_kf = int(np.count_nonzero(kf_index >= 0))
        stats["n_tracked_keyframe"] = n_tracked_kf
        dt_kf = None if self._kf_t is None else (timestamp_ns - self._kf_t) * 1e-9
        decision = decide_keyframe(cfg.keyframe, n_tracked_kf, self._kf_n, dt_kf)
        fresh = ids < 0
        stats.update(n_new=int(fresh.sum()), n_features=n)
        ids[fresh] = self._new_ids(int(fresh.sum()))
        if decision.is_keyframe:
            self._kf_id += 1
            self._kf_t = timestamp_ns
            self._kf_n = n
            kf_index = np.arange(n, dtype=np.int32)
        self._ids, self._kf_index, self._pts = ids, kf_index, kps
        self._levels = feats.levels.copy()
        self._desc = feats.descriptors
        return self._emit(
            timestamp_ns,
            decision.is_keyframe,
            decision.reason,
            survived,
            feats.descriptors,
            feats.angles,
            stats,
            t_start,
        )

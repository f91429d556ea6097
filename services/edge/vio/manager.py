"""The front object of one robot's VIO: ``feed_imu`` / ``feed_frame`` / ``get_state``.

Pipeline per frame: undistort → (no map) monocular initialisation on robot keyframes →
tracking (IMU-predicted, PnP RANSAC fallback, motion-only optimisation) → on a robot keyframe:
keyframe insertion, association, triangulation, local BA, and the scheduled visual-inertial
initialisations (first at ``vi_init.first_after_s``, re-runs at ``vi_init.refine_after_s``;
:mod:`services.edge.vio.vi_schedule`).
Tracking loss: the IMU bridges short gaps, a VI map is kept a while for robot keyframes to
relocalise in, then a new map starts (:mod:`services.edge.vio.tracking_loss`). Everything runs
synchronously in the caller.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace

import numpy as np

from common.calibration import CameraCalibration, ImuCalibration
from common.geometry import inverse_T, make_T, orthonormalize_T
from common.imu import ImuBuffer, ImuDataError, ImuSegment, with_measured_noise
from common.preintegration import (
    integrate_gyro,
    make_preintegration_params,
    predict_state,
    preintegrate,
)
from services.edge.vio.local_ba import BAStats, bundle_adjust
from services.edge.vio.local_mapping import (
    associate_keyframe,
    match_by_projection,
    triangulate_new_points,
)
from services.edge.vio.mono_init import two_view_geometry
from services.edge.vio.relocalisation import search_local_map, with_found
from services.edge.vio.state import Keyframe, MapPoint, PinholeUndistorter, VioMap
from services.edge.vio.time_offset import TimeOffsetTracker
from services.edge.vio.tracking import ImuPrior, TrackResult, track_with_fallback
from services.edge.vio.tracking_loss import TrackingLoss, VioFrame
from services.edge.vio.types import (
    FrameObservation,
    FrameResult,
    MapUpdate,
    TrackingStatus,
    VioConfig,
    VioError,
    VioState,
    VioStats,
)
from services.edge.vio.vi_schedule import ViInitSchedule

logger = logging.getLogger(__name__)


class VioManager(ViInitSchedule, TrackingLoss):
    """Monocular-inertial VIO of one robot (ORB-SLAM3-style, gtsam back end)."""

    def __init__(
        self,
        camera: CameraCalibration,
        imu: ImuCalibration,
        options: VioConfig | None = None,
        robot_name: str = "robot",
    ) -> None:
        self.options = options or VioConfig()
        self.camera = PinholeUndistorter(camera)
        if not np.allclose(imu.T_body_imu, np.eye(4)):
            # Body frame = IMU frame: express the camera extrinsic relative to the IMU.
            self.camera.T_body_cam = inverse_T(np.array(imu.T_body_imu)) @ self.camera.T_body_cam
            self.camera.T_cam_body = inverse_T(self.camera.T_body_cam)
        self.imu_calibration = imu
        self.imu_params = make_preintegration_params(
            imu, self.options.gravity_mps2, self.options.integration_sigma
        )
        self.name = robot_name
        self.stats = VioStats()
        # The newest imu_history_s of samples, on the IMU's clock: preintegration, the noise
        # measurement, the time offset estimate and re-slicing keyframes after it moves.
        self._imu = ImuBuffer(horizon_s=self.options.imu_history_s)
        self._time_offset = TimeOffsetTracker(
            self.options.time_offset,
            self.options.time_offset_ns,
            enabled=self.options.estimate_time_offset,
        )
        self.stats.time_offset_ms = self.options.time_offset_ns * 1e-6
        self._map: VioMap | None = None
        self._next_map_id = 0
        self._next_kf_id = 0
        self._ref: VioFrame | None = None
        self._last_T: np.ndarray | None = None
        self._prev_T: np.ndarray | None = None
        self._last_t: int | None = None
        self._last_v: np.ndarray | None = None
        self._last_bias: tuple[np.ndarray, np.ndarray] | None = None
        self._bias_guess = (np.zeros(3), np.zeros(3))  # (accel, gyro) carried to new maps
        self._pending_updates: list[MapUpdate] = []
        self._point_moves: list[tuple[int, dict[int, np.ndarray]]] = []
        self._last_init_reason = ""
        self.last_local_ba: BAStats | None = None
        self._keyframes_since_ba = 0
        self._lost_since: int | None = None  # first frame of a recently lost run [ns]
        self._unheld: set[int] = set()  # bridge keyframes of the map that found too few points
        # VI initialisation and its refinements optimise every keyframe and every point.
        self._full_ba_options = replace(self.options.local_ba, max_points=0)
        logger.info("VIO %s options: %s", robot_name, self.options)

    # ------------------------------------------------------------------ public API
    @property
    def initialized(self) -> bool:
        """True once the current map is metric and gravity-aligned (VI init done)."""
        return self._map is not None and self._map.vi_initialized

    @property
    def map_id(self) -> int:
        return self._map.map_id if self._map is not None else self._next_map_id

    @property
    def current_map(self) -> VioMap | None:
        return self._map

    def feed_imu(self, timestamps_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        """Append IMU samples: (K,) int64 ns, (K, 3) rad/s, (K, 3) m/s² in the IMU frame."""
        try:
            self._imu.append(timestamps_ns, gyro, accel)
        except ImuDataError as exc:
            raise VioError(f"feed_imu: {exc}") from exc

    @property
    def time_offset_ns(self) -> int:
        """The camera-IMU time offset in use: ``t_imu = t_cam + offset`` [ns]."""
        return self._time_offset.offset_ns

    def measure_imu_noise(self) -> bool:
        """Measure the white-noise densities (gyro rad/s/√Hz, accel m/s²/√Hz) the newest samples
        show (:func:`common.imu.measured_noise_density`, kept in ``stats``) and set the
        preintegration noise from them where they exceed the calibration
        (``VioConfig.noise_from_data``); True when the IMU is now weighted by measured noise.
        Run at each VI
        initialisation and refinement, so the IMU is weighted as the sensor behaves in flight,
        not as its datasheet says (a real ADIS16448 on a MAV: 25-33x gyro, 40-60x accel)."""
        gyro_nd, accel_nd = self._imu.noise_density(self.options.noise_window_samples)
        self.stats.imu_noise_measured = (gyro_nd, accel_nd)
        if not self.options.noise_from_data:
            return False
        calib = with_measured_noise(self.imu_calibration, gyro_nd, accel_nd)
        self.imu_params = make_preintegration_params(
            calib, self.options.gravity_mps2, self.options.integration_sigma
        )
        self.stats.imu_noise_used = (calib.gyro_noise_density, calib.accel_noise_density)
        return calib is not self.imu_calibration

    def feed_frame(self, obs: FrameObservation) -> FrameResult:
        """Process one frame (feed its IMU samples first) and return its estimate."""
        if not isinstance(obs, FrameObservation):
            raise VioError(f"feed_frame expects a FrameObservation, got {type(obs).__name__}")
        if self._last_t is not None and obs.timestamp_ns <= self._last_t:
            raise VioError(
                f"feed_frame: timestamp {obs.timestamp_ns} not after previous {self._last_t}"
            )
        xy = self.camera.normalise(obs.keypoints_px)
        seen = np.isfinite(xy).all(axis=1)
        n_rows, rows = len(xy), None
        if not seen.all():  # a fisheye's rays at 90 degrees and more: no normalised point
            obs = obs.subset(seen)
            xy = xy[seen]
            rows = np.flatnonzero(seen)  # the robot's rows, for what leaves the VIO
        sigma = (
            self.options.pixel_sigma
            * self.options.level_scale ** obs.levels.astype(np.float64)
            / self.camera.focal
        )
        frame = VioFrame(obs, xy, sigma, rows, n_rows)
        if self._map is None:
            result = self._initialise_mono(frame)
        else:
            result = self._track(frame)
        self._last_t = obs.timestamp_ns
        return result

    def get_state(self) -> VioState | None:
        """Latest inertial state for feedback to the robot, or None before VI initialisation."""
        if not self.initialized or self._last_T is None or self._last_v is None:
            return None
        ba, bg = self._last_bias if self._last_bias is not None else self._bias_guess
        g_world = np.array([0.0, 0.0, -self.options.gravity_mps2])
        return VioState(
            timestamp_ns=int(self._last_t or 0),
            map_id=self.map_id,
            T_world_body=self._last_T.copy(),
            v_world=self._last_v.copy(),
            bias_gyro=bg.copy(),
            bias_accel=ba.copy(),
            gravity_body=self._last_T[:3, :3].T @ g_world,
        )

    def pop_map_updates(self) -> list[MapUpdate]:
        """Changes of keyframes and map points (per map) since the previous call, of
        VI-initialised maps only: before its VI initialisation a map has its own scale and no
        gravity, and the cloud would merge maps into it (a map that dies before, e.g. on a
        killed edge, stayed there as the frame of the whole atlas: 8 deg off gravity, 10 m
        off); its changes wait, and go up at once when it is initialised."""
        out = self._pending_updates
        self._pending_updates = []
        if self._map is not None and self._map.vi_initialized:
            upd = self._collect_update(self._map)
            if upd.keyframes or upd.points or upd.removed_point_ids:
                out.append(upd)
        return out

    def pop_point_moves(self) -> list[tuple[int, dict[int, np.ndarray]]]:
        """The corrections applied since the last call, as ``(map id, {keyframe id: (4, 4)
        correction})``: each map point moved with the correction of its first observer (the
        uplink moves the points it holds back the same way)."""
        moves, self._point_moves = self._point_moves, []
        return moves

    def apply_pose_corrections(self, map_id: int, T_world_body: dict[int, np.ndarray]) -> int:
        """Apply corrected keyframe poses (e.g. from the cloud's global optimisation, same world
        frame) to the current map: each corrected keyframe takes its pose, uncorrected ones move
        with the nearest earlier corrected keyframe, each map point moves rigidly with its first
        observer (nothing re-sent to the cloud), and the tracking state with the newest keyframe.
        Returns keyframes updated;
        corrections for another map are ignored (0), and so are those of a map before its VI
        initialisation: the cloud's poses are in the metric, gravity-aligned frame it got the
        map in, a visual map has its own scale until then (e.g. the re-run of a map that a
        restarted edge replays from its journal while the cloud still corrects the first run,
        which broke its initialisation: "IMU and visual poses disagree", the map 17 m off)."""
        vmap = self._map
        if vmap is None or vmap.map_id != map_id or not vmap.vi_initialized:
            return 0
        delta = np.eye(4)
        deltas: dict[int, np.ndarray] = {}
        n = 0
        for kf in vmap.keyframe_list():
            T_new = T_world_body.get(kf.id)
            if T_new is not None:
                T_new = np.asarray(T_new, dtype=np.float64)
                if T_new.shape != (4, 4) or not np.all(np.isfinite(T_new)):
                    raise VioError(f"apply_pose_corrections: keyframe {kf.id} pose is not (4, 4)")
                # Snap rotations back onto SO(3): repeated corrections otherwise compound the
                # float error until the cloud refuses the poses as not orthonormal.
                delta = orthonormalize_T(orthonormalize_T(T_new) @ inverse_T(kf.T_world_body))
                n += 1
            deltas[kf.id] = delta
            kf.T_world_body = orthonormalize_T(delta @ kf.T_world_body)
            kf.v_world = delta[:3, :3] @ kf.v_world
        for mp in vmap.points.values():
            ref = min(mp.observations, default=None)
            if ref is not None and ref in deltas:
                mp.p_world = deltas[ref][:3, :3] @ mp.p_world + deltas[ref][:3, 3]
        self._point_moves.append((map_id, deltas))
        # Nothing is re-marked for the uplink: the cloud computed these poses and moved its
        # points with them; resending every point and keyframe of the map after each
        # correction was ~90 % of the edge->cloud bytes. What local BA touches next goes up
        # again anyway.
        if self._last_T is not None:
            self._last_T = orthonormalize_T(delta @ self._last_T)
        if self._prev_T is not None:
            self._prev_T = orthonormalize_T(delta @ self._prev_T)
        if self._last_v is not None:
            self._last_v = delta[:3, :3] @ self._last_v
        return n

    # ------------------------------------------------------------------ helpers
    def _collect_update(self, vmap: VioMap) -> MapUpdate:
        kfs, pts, removed = vmap.pop_changes()
        return MapUpdate(
            map_id=vmap.map_id,
            vi_initialized=vmap.vi_initialized,
            keyframes=tuple(vmap.keyframe_snapshot(vmap.keyframes[k]) for k in kfs),
            points=vmap.point_batch(pts),
            removed_point_ids=tuple(removed),
        )

    def _segment(self, t0_ns: int, t1_ns: int) -> ImuSegment | None:
        """The IMU between two camera times (read at ``t + time offset`` on the IMU clock), or
        None if the buffer does not reach. The newest sample is held for up to
        ``time_offset.max_offset_ms`` past it: until the robot batches by the offset, a frame's
        IMU ends at the frame, not at ``t + offset``."""
        td = self._time_offset.offset_ns
        a, b = t0_ns + td, t1_ns + td
        seg = self._imu.segment(a, b)
        last = self._imu.last_timestamp_ns
        hold = int(self.options.time_offset.max_offset_ms * 1e6)
        if seg is None and self._imu.covers(a, a) and last is not None and last >= b - hold:
            seg = self._imu.held_segment(a, b) if b > a else None
        return seg

    def update_time_offset(self, vmap: VioMap, force: bool = False, adopt: bool = False) -> bool:
        """Estimate the camera-IMU time offset when due (``force``: now, at most once per
        ``every_s``; ``adopt``: now, and take an unconfident estimate that rejects the offset
        in use, ``vi_init.adopt_time_offset_*``); when it moved,
        re-slice the IMU of the map's keyframes the buffer still holds. True if it moved."""
        bias = self._last_bias[1] if self._last_bias is not None else self._bias_guess[1]
        buf = self._imu
        new = self._time_offset.update(buf.timestamps_ns, buf.gyro, bias, force, adopt)
        if new is None and adopt:
            vopt = self.options.vi_init
            k, floor = vopt.adopt_time_offset_sigmas, vopt.adopt_time_offset_min_ms
            new = self._time_offset.adopt_last(k, floor)
        if (est := self._time_offset.last) is not None:
            self.stats.time_offset_sigma_ms = est.sigma_ms
        if new is None:
            return False
        self.stats.time_offset_ms = new * 1e-6
        for kf in vmap.keyframe_list():
            if kf.previous_id is not None and kf.previous_id in vmap.keyframes:
                seg = self._segment(vmap.keyframes[kf.previous_id].timestamp_ns, kf.timestamp_ns)
                if seg is not None:
                    kf.imu_from_previous = seg
        return True

    def _result(
        self,
        frame: VioFrame,
        T: np.ndarray | None,
        status: TrackingStatus,
        n_inl: int,
        is_kf: bool,
        reason: str = "",
    ) -> FrameResult:
        T = np.eye(4) if T is None else np.array(T)
        return FrameResult(frame.obs.timestamp_ns, T, status, self.map_id, n_inl, is_kf, reason)

    def _new_keyframe(
        self, frame: VioFrame, T_world_body: np.ndarray, previous: Keyframe | None
    ) -> Keyframe:
        seg = None
        if previous is not None:
            seg = self._segment(previous.timestamp_ns, frame.obs.timestamp_ns)
        kf = Keyframe(
            id=self._next_kf_id,
            timestamp_ns=frame.obs.timestamp_ns,
            T_world_body=np.array(T_world_body, dtype=np.float64),
            track_ids=frame.obs.track_ids,
            xy=frame.xy,
            sigma=frame.sigma,
            keypoints_px=frame.obs.keypoints_px,
            levels=frame.obs.levels,
            descriptors=frame.obs.descriptors,
            previous_id=None if previous is None else previous.id,
            imu_from_previous=seg,
            robot_rows=frame.rows,
            n_robot_rows=frame.n_rows,
        )
        self._next_kf_id += 1
        return kf

    # ------------------------------------------------------------------ mono init
    def _initialise_mono(self, frame: VioFrame) -> FrameResult:
        opt = self.options.mono_init
        st = TrackingStatus.INITIALIZING
        own = self.options.max_keyframe_interval_s
        candidate = frame.obs.is_keyframe or (
            own > 0
            and (
                self._ref is None
                or (frame.obs.timestamp_ns - self._ref.obs.timestamp_ns) * 1e-9 >= own
            )
        )
        if not candidate:
            why = "waiting for a keyframe"
            if self._last_init_reason:
                why += f" (last attempt: {self._last_init_reason})"
            return self._result(frame, None, st, 0, False, why)
        ref = self._ref
        too_old = (
            ref is not None
            and (frame.obs.timestamp_ns - ref.obs.timestamp_ns) * 1e-9 > opt.max_reference_age_s
        )
        if ref is None or len(ref.obs.track_ids) < opt.min_tracks or too_old:
            self._ref = frame
            return self._result(frame, None, st, 0, False, "reference keyframe set")
        _, i_ref, i_cur = np.intersect1d(
            ref.obs.track_ids, frame.obs.track_ids, assume_unique=True, return_indices=True
        )
        tv, reason = two_view_geometry(ref.xy[i_ref], frame.xy[i_cur], self.camera.focal, opt)
        self._last_init_reason = f"mono init: {reason}" if reason else ""
        if tv is None:
            if len(i_ref) < opt.min_tracks:
                self._ref = frame
            return self._result(frame, None, st, 0, False, f"mono init: {reason}")
        # Build the first map: body of the reference keyframe at the origin.
        vmap = VioMap(self._next_map_id)
        self._next_map_id += 1
        T_b_c = self.camera.T_body_cam
        T_w_c0 = T_b_c.copy()
        T_w_c1 = T_w_c0 @ inverse_T(make_T(tv.R_c1_c0, tv.t_c1_c0))
        kf0 = self._new_keyframe(ref, np.eye(4), None)
        vmap.add_keyframe(kf0)
        kf1 = self._new_keyframe(frame, T_w_c1 @ self.camera.T_cam_body, kf0)
        vmap.add_keyframe(kf1)
        p_world = tv.p_c0 @ T_w_c0[:3, :3].T + T_w_c0[:3, 3]
        for k in np.flatnonzero(tv.good):
            tid = int(ref.obs.track_ids[i_ref[k]])
            obs = {kf0.id: int(i_ref[k]), kf1.id: int(i_cur[k])}
            desc = None if ref.obs.descriptors is None else ref.obs.descriptors[i_ref[k]]
            vmap.add_point(MapPoint(tid, p_world[k], obs, desc))
        bundle_adjust(
            vmap,
            [kf0.id, kf1.id],
            self.camera,
            None,
            self.options.local_ba,
            self.options.mapping,
            gauge_ids=(kf0.id, kf1.id),
        )
        self._map = vmap
        self._ref = None
        self._prev_T = kf0.T_world_body.copy()
        self._last_T = kf1.T_world_body.copy()
        logger.info(
            "%s: map %d initialised (%s, %d points, parallax %.1f deg)",
            self.name,
            vmap.map_id,
            tv.model,
            len(vmap.points),
            tv.median_parallax_deg,
        )
        return self._result(
            frame,
            kf1.T_world_body,
            st,
            len(vmap.points),
            True,
            "visual map initialised; waiting for VI initialisation",
        )

    # ------------------------------------------------------------------ tracking
    def _predict(
        self, frame: VioFrame, vmap: VioMap
    ) -> tuple[np.ndarray, np.ndarray | None, ImuPrior | None]:
        """(T_pred, v_pred, ImuPrior | None) for the frame."""
        t = frame.obs.timestamp_ns
        last_kf = vmap.last_keyframe()
        assert last_kf is not None and self._last_T is not None
        if vmap.vi_initialized:
            seg = self._segment(last_kf.timestamp_ns, t)
            if seg is not None:
                pim = preintegrate(self.imu_params, seg, last_kf.bias_accel, last_kf.bias_gyro)
                T, v = predict_state(
                    pim,
                    last_kf.T_world_body,
                    last_kf.v_world,
                    last_kf.bias_accel,
                    last_kf.bias_gyro,
                )
                return T, v, ImuPrior(last_kf, pim)
        # Constant velocity; rotation from the gyro when available.
        T_pred = self._last_T.copy()
        if self._prev_T is not None:
            T_pred = self._last_T @ (inverse_T(self._prev_T) @ self._last_T)
        if self._last_t is not None:
            seg = self._segment(self._last_t, t)
            if seg is not None:
                T_pred[:3, :3] = self._last_T[:3, :3] @ integrate_gyro(seg, self._bias_guess[1])
        return T_pred, None, None

    def _track(self, frame: VioFrame) -> FrameResult:
        vmap = self._map
        assert vmap is not None
        t_start = time.perf_counter()
        ids = frame.obs.track_ids
        mps = [vmap.point_of(t) for t in ids.tolist()]
        has = np.array([mp is not None for mp in mps], dtype=bool)
        P = np.array([mp.p_world for mp in mps if mp is not None]).reshape(-1, 3)
        T_pred, v_pred, prior = self._predict(frame, vmap)
        args = (frame.xy, frame.sigma, ids, self.camera, self.options.tracking)
        res, reason = track_with_fallback(P, has, *args, T_pred, prior, v_pred)
        if res is None and vmap.vi_initialized and frame.obs.descriptors is not None:
            seen = {mp.id for mp in mps if mp is not None}
            found = search_local_map(
                vmap, frame.obs, frame.xy, has, seen, T_pred, self.camera, self.options
            )
            P, has = with_found(vmap, P, has, found)
            res, why = track_with_fallback(P, has, *args, T_pred, prior, v_pred)
            logger.debug("%s: relocalise: %d found by projection: %s", self.name, len(found), why)
        self.stats.track_s.append(time.perf_counter() - t_start)
        if res is None:
            if prior is not None and v_pred is not None:
                return self._bridge(frame, vmap, T_pred, v_pred, prior, reason)
            return self._lose(frame, vmap, reason)
        t = frame.obs.timestamp_ns
        if self._lost_since is not None:
            self.stats.relocalised += 1
            logger.info(
                "%s: map %d tracked again after %.1f s lost",
                self.name,
                vmap.map_id,
                (t - self._lost_since) * 1e-9,
            )
            self._lost_since = None
        self._prev_T, self._last_T = self._last_T, res.T_world_body
        R_visual = res.T_world_body if res.R_world_body_visual is None else res.R_world_body_visual
        self._time_offset.add_frame(frame.obs.timestamp_ns, R_visual, vmap.map_id)
        if res.v_world is not None:
            assert res.bias_accel is not None and res.bias_gyro is not None  # set with v_world
            self._last_v = res.v_world
            self._last_bias = (res.bias_accel, res.bias_gyro)
        n_inl = len(res.inlier_ids)
        is_kf = False
        T_out = res.T_world_body
        last_kf = vmap.last_keyframe()
        assert last_kf is not None
        if self._keyframe_due(frame, last_kf, vmap, n_inl):
            kf = self._insert_keyframe(frame, res, vmap, last_kf)
            is_kf = True
            T_out = kf.T_world_body
            self._last_T = kf.T_world_body.copy()
            if vmap.vi_initialized:
                self._last_v = kf.v_world.copy()
                self._last_bias = (kf.bias_accel.copy(), kf.bias_gyro.copy())
        if vmap.vi_initialized:
            return self._result(frame, T_out, TrackingStatus.TRACKING, n_inl, is_kf)
        why = "visual-only map (arbitrary scale); VI initialisation pending"
        if self._last_init_reason.startswith("VI init"):
            why += f" ({self._last_init_reason})"
        return self._result(frame, T_out, TrackingStatus.INITIALIZING, n_inl, is_kf, why)

    def _keyframe_due(self, frame: VioFrame, last_kf: Keyframe, vmap: VioMap, n_inl: int) -> bool:
        """Robot keyframes, and the VIO's own ones (see ``VioConfig.max_keyframe_interval_s``)."""
        opt = self.options
        dt = (frame.obs.timestamp_ns - last_kf.timestamp_ns) * 1e-9
        if dt < opt.min_keyframe_interval_s:
            return False
        if frame.obs.is_keyframe:
            return True
        if opt.max_keyframe_interval_s <= 0:
            return False
        n_kf = sum(1 for t in last_kf.row_of if vmap.point_of(t) is not None)
        return dt >= opt.max_keyframe_interval_s or n_inl < opt.min_tracked_point_ratio * n_kf

    # ------------------------------------------------------------------ local mapping
    def _insert_keyframe(
        self,
        frame: VioFrame,
        res: TrackResult,
        vmap: VioMap,
        last_kf: Keyframe,
        force_ba: bool = False,
    ) -> Keyframe:
        kf = self._new_keyframe(frame, res.T_world_body, last_kf)
        if res.v_world is not None:
            assert res.bias_accel is not None and res.bias_gyro is not None  # set with v_world
            kf.v_world = res.v_world.copy()
            kf.bias_accel = res.bias_accel.copy()
            kf.bias_gyro = res.bias_gyro.copy()
        else:
            kf.bias_accel, kf.bias_gyro = (b.copy() for b in self._bias_guess)
        vmap.add_keyframe(kf)
        mopt = self.options.mapping
        associate_keyframe(vmap, kf, self.camera, mopt)
        if mopt.match_by_projection:
            match_by_projection(vmap, kf, self.camera, mopt)
        n_new = triangulate_new_points(vmap, kf, self.camera, mopt)
        self.update_time_offset(vmap)
        self._keyframes_since_ba += 1
        if (
            not frame.obs.is_keyframe
            and not force_ba
            and self._keyframes_since_ba < self.options.local_ba.every_keyframes
        ):
            self._maybe_vi_init(vmap)
            return kf
        self._keyframes_since_ba = 0
        t0 = time.perf_counter()
        window = [k.id for k in vmap.keyframe_list()[-self.options.local_ba.window_size :]]
        first_ids = tuple(k.id for k in vmap.keyframe_list()[:2])
        gauge = first_ids[:1]  # scale gauge before VI init: held by LM damping only
        use_imu = vmap.vi_initialized and all(
            vmap.keyframes[k].imu_from_previous is not None for k in window[1:]
        )
        self.last_local_ba = bundle_adjust(
            vmap,
            window,
            self.camera,
            self.imu_params if use_imu else None,
            self.options.local_ba,
            mopt,
            gauge_ids=gauge,
        )
        self.stats.local_ba_s.append(time.perf_counter() - t0)
        logger.debug("%s: KF %d, %d new points, BA %s", self.name, kf.id, n_new, self.last_local_ba)
        self._maybe_vi_init(vmap)
        return kf

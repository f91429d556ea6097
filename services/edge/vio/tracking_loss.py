"""What the VIO does when a frame's tracks no longer hold its map.

:class:`TrackingLoss` is a base of :class:`~services.edge.vio.manager.VioManager` (which sets
the attributes declared here). In order:

1. **the IMU bridge** (``TrackingConfig.imu_bridge_s``): too few tracks on map points within
   that long of the map's last keyframe (new ground seen through the sparse frames an uplink
   budget leaves): the frame becomes a keyframe at the IMU's prediction, its tracks that
   earlier keyframes saw are triangulated and the visual-inertial local BA refines it, as
   VINS-Mono's sliding window does with every frame. A bridge that found too few points
   leaves its keyframe in the map, and while the map is recently lost the next frame bridges
   from it (``TrackingConfig.bridge_while_lost``): the tracks the two share are triangulated
   between their IMU poses, and the map is tracked again without a new map;
2. **recently lost** (``TrackingConfig.recently_lost_s``, ORB-SLAM3's RECENTLY_LOST): a VI map
   is kept while the IMU predicts; each robot keyframe meanwhile tries to relocalise in it by
   projection (:mod:`services.edge.vio.relocalisation`, called from tracking);
3. then **a new map** (new ``map_id``), which the cloud merges by place recognition.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from common.calibration import ImuCalibration
from services.edge.vio.state import Keyframe, VioMap
from services.edge.vio.tracking import ImuPrior, TrackResult
from services.edge.vio.types import (
    FrameObservation,
    FrameResult,
    MapUpdate,
    TrackingStatus,
    VioConfig,
    VioStats,
)

logger = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class VioFrame:
    """A frame as the VIO uses it: ``obs`` the features it can use, ``xy`` (N, 2) their
    normalised coordinates, ``sigma`` (N,) their noise; ``rows`` (N,) the row of each in the
    robot's frame when some were left out (None: all, in order) and ``n_rows`` how many that
    frame has."""

    obs: FrameObservation
    xy: np.ndarray
    sigma: np.ndarray
    rows: np.ndarray | None = None
    n_rows: int = 0


class TrackingLoss:
    """Tracking-loss handling of :class:`~services.edge.vio.manager.VioManager`."""

    options: VioConfig
    stats: VioStats
    name: str
    imu_calibration: ImuCalibration
    _map: VioMap | None
    _next_map_id: int
    _ref: VioFrame | None
    _lost_since: int | None
    _unheld: set[int]
    _last_init_reason: str
    _last_T: np.ndarray | None
    _prev_T: np.ndarray | None
    _last_v: np.ndarray | None
    _last_bias: tuple[np.ndarray, np.ndarray] | None
    _bias_guess: tuple[np.ndarray, np.ndarray]
    _pending_updates: list[MapUpdate]

    def _result(  # VioManager's
        self,
        frame: VioFrame,
        T: np.ndarray | None,
        status: TrackingStatus,
        n_inl: int,
        is_kf: bool,
        reason: str = "",
    ) -> FrameResult:
        raise NotImplementedError

    def _insert_keyframe(  # VioManager's
        self,
        frame: VioFrame,
        res: TrackResult,
        vmap: VioMap,
        last_kf: Keyframe,
        force_ba: bool = False,
    ) -> Keyframe:
        raise NotImplementedError

    def _collect_update(self, vmap: VioMap) -> MapUpdate:  # VioManager's
        raise NotImplementedError

    def _lose(self, frame: VioFrame, vmap: VioMap, reason: str) -> FrameResult:
        """Tracking failed: a VI map is kept for ``recently_lost_s``, then a new map."""
        t = frame.obs.timestamp_ns
        self._lost_since = t if self._lost_since is None else self._lost_since
        kept_s = (t - self._lost_since) * 1e-9
        if vmap.vi_initialized and kept_s < self.options.tracking.recently_lost_s:
            self.stats.frames_lost_kept += 1
            why = f"lost: {reason}; map {vmap.map_id} kept for {kept_s:.1f} s (IMU)"
            return self._result(frame, None, TrackingStatus.LOST, 0, False, why)
        self._start_new_map(frame, reason)
        return self._result(frame, None, TrackingStatus.LOST, 0, False, f"lost: {reason}")

    def _bridge(
        self,
        frame: VioFrame,
        vmap: VioMap,
        T_pred: np.ndarray,
        v_pred: np.ndarray,
        prior: ImuPrior,
        reason: str,
    ) -> FrameResult:
        """Too few of the frame's tracks have map points (new ground seen through sparse frames,
        e.g. under an uplink budget): while the IMU alone holds, the frame becomes a keyframe
        at the IMU's prediction, its tracks that earlier keyframes saw are triangulated and the
        visual-inertial local BA refines it (VINS-Mono's sliding window has no other way: its
        features are triangulated from IMU-propagated poses). Else the map is recently lost."""
        t = frame.obs.timestamp_ns
        kf0 = prior.keyframe
        opt = self.options.tracking
        lost = self._lost_since is not None
        # IMU-only time: since the newest keyframe the map held (a failed bridge's does not)
        held = next((k for k in reversed(vmap.keyframes.values()) if k.id not in self._unheld), kf0)
        imu_only_s = (t - held.timestamp_ns) * 1e-9
        if (
            (not lost or opt.bridge_while_lost)
            and 0 < (t - kf0.timestamp_ns) * 1e-9 <= opt.imu_bridge_s
            and imu_only_s <= self.imu_only_limit_s()
            and len(frame.obs.track_ids) >= opt.min_inliers
        ):
            res = TrackResult(T_pred, v_pred, kf0.bias_accel, kf0.bias_gyro, np.zeros(0), False)
            kf = self._insert_keyframe(frame, res, vmap, kf0, force_ba=True)
            n = sum(1 for tr in kf.row_of if vmap.point_of(tr) is not None)
            if n < opt.min_inliers:
                self._unheld.add(kf.id)
            else:
                self.stats.frames_bridged += 1
                if self._lost_since is not None:
                    lost_s = (t - self._lost_since) * 1e-9
                    logger.info(
                        "%s: map %d bridged again after %.1f s lost", self.name, vmap.map_id, lost_s
                    )
                    self.stats.bridged_back += 1
                    self._lost_since = None
                self._prev_T, self._last_T = self._last_T, kf.T_world_body.copy()
                self._last_v = kf.v_world.copy()
                self._last_bias = (kf.bias_accel.copy(), kf.bias_gyro.copy())
                why = f"IMU-bridged keyframe ({reason}): {n} map points after BA"
                return self._result(frame, kf.T_world_body, TrackingStatus.TRACKING, n, True, why)
        return self._lose(frame, vmap, reason)

    def imu_only_limit_s(self) -> float:
        """How long [s] after the newest keyframe the map held a bridge may still place a
        keyframe from the IMU alone: while the position the IMU predicts stays within
        ``TrackingConfig.bridge_max_sigma_m`` (1 sigma) under the accelerometer white noise
        the VIO weighs it by (``VioStats.imu_noise_used``, else the calibration's), sigma_p =
        sigma_a * sqrt(t^3 / 3); unbounded when that is 0."""
        opt = self.options.tracking
        sigma_a = self.stats.imu_noise_used[1]
        if not np.isfinite(sigma_a):
            sigma_a = self.imu_calibration.accel_noise_density
        if opt.bridge_max_sigma_m <= 0 or sigma_a <= 0:
            return float("inf")
        return float((3.0 * (opt.bridge_max_sigma_m / sigma_a) ** 2) ** (1 / 3))

    def _start_new_map(self, frame: VioFrame | None, reason: str) -> None:
        if self._map is not None:
            if self._map.vi_initialized and self._last_bias is not None:
                self._bias_guess = self._last_bias
            if self._map.vi_initialized:  # (one that never was never leaves the edge)
                self._pending_updates.append(self._collect_update(self._map))
            logger.warning(
                "%s: map %d lost (%s); starting map %d",
                self.name,
                self._map.map_id,
                reason,
                self._next_map_id,
            )
        self._map = None
        self._last_init_reason = ""
        own = self.options.max_keyframe_interval_s > 0
        self._ref = frame if frame is not None and (own or frame.obs.is_keyframe) else None
        self._last_T = self._prev_T = self._last_v = None
        self._last_bias = None
        self._lost_since = None
        self._unheld = set()
        self.stats.maps_started += 1

"""When the VIO runs a map's visual-inertial initialisation, and what it keeps of it.

:class:`ViInitSchedule` is a base of :class:`~services.edge.vio.manager.VioManager` (which sets
the attributes declared here). At each new keyframe ``_maybe_vi_init`` decides: the first VI
initialisation once the map spans ``vi_init.first_after_s`` with ``vi_init.min_keyframes``
keyframes (a refused one is retried ``vi_init.retry_interval_s`` later; while the camera-IMU
offset is estimated and not yet confident, up to ``vi_init.wait_for_time_offset_s`` later;
without a confident offset it then takes an estimate made at that moment that rejects the offset
in use, ``vi_init.adopt_time_offset_sigmas``),
then a refinement at each map age of ``vi_init.refine_after_s``, and at once when the offset
moved by ``vi_init.refine_on_offset_change_ms`` since the last one.
:meth:`ViInitSchedule.run_vi_init` runs one (:mod:`services.edge.vio.vi_bootstrap`) over the
longest tail of keyframes linked by IMU segments and keeps the reasons, the bias guess for new
maps and the statistics.
"""

from __future__ import annotations

import logging
import time

import gtsam
import numpy as np

from services.edge.vio.state import PinholeUndistorter, VioMap
from services.edge.vio.time_offset import TimeOffsetTracker
from services.edge.vio.types import LocalBAConfig, VioConfig, VioStats
from services.edge.vio.vi_bootstrap import first_vi_init, refine_vi

logger = logging.getLogger(__name__)


class ViInitSchedule:
    """The VI initialisation schedule of :class:`~services.edge.vio.manager.VioManager`."""

    options: VioConfig
    camera: PinholeUndistorter
    imu_params: gtsam.PreintegrationCombinedParams
    name: str
    stats: VioStats
    _last_T: np.ndarray | None
    _last_init_reason: str
    _bias_guess: tuple[np.ndarray, np.ndarray]  # (accel, gyro)
    _full_ba_options: LocalBAConfig
    _time_offset: TimeOffsetTracker

    def measure_imu_noise(self) -> bool:  # VioManager's
        raise NotImplementedError

    def update_time_offset(  # VioManager's
        self, vmap: VioMap, force: bool = False, adopt: bool = False
    ) -> bool:
        raise NotImplementedError

    def _maybe_vi_init(self, vmap: VioMap) -> None:
        vopt = self.options.vi_init
        kfs = vmap.keyframe_list()
        age = (kfs[-1].timestamp_ns - kfs[0].timestamp_ns) * 1e-9
        runs = vmap.vi_init_runs
        if runs == 0:
            last = vmap.last_vi_attempt_ns
            waited = last is None or (kfs[-1].timestamp_ns - last) * 1e-9 >= vopt.retry_interval_s
            due = age >= vopt.first_after_s and len(kfs) >= vopt.min_keyframes and waited
            if due:
                self.update_time_offset(vmap, force=True)  # before the IMU is first used
                offset = self._time_offset
                waiting = age < vopt.first_after_s + vopt.wait_for_time_offset_s
                if offset.enabled and not offset.confident and waiting:
                    est = f" (last estimate {offset.last})" if offset.last is not None else ""
                    self._last_init_reason = f"VI init waits for the camera-IMU offset{est}"
                    return
                vmap.last_vi_attempt_ns = kfs[-1].timestamp_ns
                if offset.enabled and not offset.confident:
                    self.update_time_offset(vmap, adopt=vopt.adopt_time_offset_sigmas > 0)
        else:
            moved_ms = abs(self._time_offset.offset_ns - vmap.vi_time_offset_ns) * 1e-6
            limit = vopt.refine_on_offset_change_ms
            if limit > 0 and moved_ms >= limit:
                logger.info(
                    "%s: map %d: time offset moved %.1f ms since its VI init: refined now",
                    self.name,
                    vmap.map_id,
                    moved_ms,
                )
                runs = vmap.vi_init_runs
                self.run_vi_init(vmap)
                vmap.vi_init_runs = runs  # an extra run: the schedule stays as it was
                return
            due = runs <= len(vopt.refine_after_s) and age >= vopt.refine_after_s[runs - 1]
        if due:
            self.run_vi_init(vmap)

    def run_vi_init(self, vmap: VioMap) -> bool:
        """VI initialisation, or a refinement of a VI-initialised map
        (:mod:`services.edge.vio.vi_bootstrap`), over the longest tail of keyframes connected
        by IMU segments; False if the first one was refused (it is retried later)."""
        t0 = time.perf_counter()
        noise_measured = self.measure_imu_noise()
        kfs = vmap.keyframe_list()
        start = 0
        for i in range(1, len(kfs)):
            if kfs[i].imu_from_previous is None or kfs[i].previous_id != kfs[i - 1].id:
                start = i
        kfs = kfs[start:]
        ba_opt = self._full_ba_options
        vmap.vi_init_runs += 1
        vmap.vi_time_offset_ns = self._time_offset.offset_ns
        if vmap.vi_init_runs > 1:
            stats, T_fix = refine_vi(vmap, kfs, self.camera, self.imu_params, self.options, ba_opt)
            if self._last_T is not None:
                self._last_T = T_fix @ self._last_T
            self.stats.vi_init_s.append(time.perf_counter() - t0)
            logger.info(
                "%s: VI refinement #%d of map %d: %s",
                self.name,
                vmap.vi_init_runs,
                vmap.map_id,
                stats,
            )
            return True
        out = first_vi_init(
            vmap,
            kfs,
            self.camera,
            self.imu_params,
            self.options,
            ba_opt,
            self._bias_guess[1],
            noise_measured=noise_measured,
        )
        self.stats.vi_init_s.append(time.perf_counter() - t0)
        if out.reason:
            self._last_init_reason = f"VI init rejected: {out.reason}"
            logger.warning(
                "%s: VI initialisation of map %d failed: %s", self.name, vmap.map_id, out.reason
            )
            vmap.vi_init_runs = 0  # retry at the next keyframe
            return False
        self._last_init_reason = ""
        last = vmap.last_keyframe()
        assert last is not None and out.scale is not None and out.scale_sigma_rel is not None
        self._bias_guess = (last.bias_accel.copy(), last.bias_gyro.copy())
        logger.info(
            "%s: VI init #%d of map %d: scale %.4f (sigma %.1f %%), bg %s, ba %s, BA %s",
            self.name,
            vmap.vi_init_runs,
            vmap.map_id,
            out.scale,
            100 * out.scale_sigma_rel,
            np.round(last.bias_gyro, 4),
            np.round(last.bias_accel, 3),
            out.stats,
        )
        return True

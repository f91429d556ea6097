"""Per-robot monocular-inertial VIO of the edge (paper Section VI.A), no network imports.

Front object: :class:`services.edge.vio.manager.VioManager` —
``feed_imu(timestamps_ns, gyro, accel)``, ``feed_frame(FrameObservation) -> FrameResult``,
``get_state() -> VioState | None``, ``initialized``, ``map_id``,
``pop_map_updates() -> list[MapUpdate]``, ``apply_pose_corrections(map_id, {kf_id: T})``.

Modules: ``types`` (options and data), ``imu`` (buffer, preintegration), ``state`` (keyframes,
map points), ``mono_init`` (two-view E/H), ``vi_init`` (inertial-only MAP), ``tracking``
(PnP + IMU-aided motion-only optimisation), ``local_mapping`` (association, search by
projection, triangulation), ``local_ba`` (gtsam visual-inertial BA). The built-in simulator
and its run/evaluation helpers are ``sim.vio``, outside the service.
"""

import logging

logging.getLogger(__name__).addHandler(logging.NullHandler())

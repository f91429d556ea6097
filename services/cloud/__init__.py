"""Cloud tier (paper Section VI.B): the global atlas of every robot's map.

Domain blocks (sans-I/O): ``atlas`` / ``map_types`` (maps, keyframes, map points,
covisibility, spanning tree), ``place_recognition`` (BoW database, loop candidates),
``verification`` (geometric check), ``merge`` (map merging, loops), ``global_optimization``
(pose graph, gtsam), ``full_ba`` / ``inertial`` (bundle adjustment, visual-inertial with
the forwarded IMU), ``mbp`` (map backbone profiling), ``persistence`` (SQLite state),
``map_fusion`` (front object over them), ``simulation`` (synthetic world for tests).

Service: ``uplink`` (edge messages <-> domain inputs), ``app`` (reacts to messages on one
worker thread, commits before acknowledging), ``core`` (sans-I/O schedule: debounced pose
graphs, full BA, MBP, shutdown; takes ``now``, returns solve requests and corrections),
``server`` (asyncio runner of the core: lifecycle, solves in a separate process, corrections
back to the edges), ``map_source`` (the
dashboard's ``common.map_view.MapSource``), ``output`` (TUM trajectories, ATE report).
Process: ``runner`` (options, run config, run loop, dashboard wiring), started by ``recslam
cloud`` or ``python -m services.cloud``.
"""

"""Cloud tier (paper Section VI.B): the global atlas of every robot's map.

Domain rooms (sans-I/O), each a package that re-exports nothing:

- ``atlas/``: maps, keyframes, map points, covisibility, spanning tree, retired keyframes.
- ``optimization/``: pose graph and full BA (batch and incremental, visual-inertial with the
  forwarded IMU) with gtsam, map backbone profiling (MBP).
- ``fusion/``: ``uplink`` (edge messages <-> domain inputs), place recognition (BoW),
  verification, merge, and ``map_fusion`` (front object over them).
- ``store/``: ``persistence`` (SQLite state), ``recording``, ``mission``, ``output`` (TUM
  trajectories, ATE report), ``map_source`` (the dashboard's ``common.map_view.MapSource``).

Rooms import one way: ``atlas`` <- ``optimization`` <- ``fusion``; ``atlas`` <- ``store``.

Service (this folder): ``app`` (reacts to messages on one worker thread, commits before
acknowledging; its optimisation half ``app_optimization``; ``agents``, their shared records),
``core`` (sans-I/O schedule: debounced pose graphs, full BA, MBP, shutdown; takes ``now``, returns
solve requests and corrections, ``core_actions``), ``server`` (asyncio runner of the core:
lifecycle, solves in a separate process, corrections back to the edges; ``server_outputs``,
``decode_pool``, ``load``, ``child_process``), ``config``, ``stats``. Process: ``runner``
(options, run config, run loop, dashboard wiring), started by ``recslam cloud`` or ``python -m
services.cloud``. The synthetic world of the tests is ``sim.cloud``, outside the service.
"""

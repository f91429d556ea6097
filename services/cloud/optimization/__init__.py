"""Global optimisation of a map (paper Eq. 20) and map backbone profiling, with gtsam.

``global_optimization`` (pose graph), ``full_ba`` (batch bundle adjustment), ``inertial``
(its IMU terms), ``incremental_ba`` (the same on iSAM2), ``mbp`` (map backbone profiling).
Imports only the ``atlas`` room. Nothing is re-exported here: import from the modules.
"""

"""Simulators and link tools on the lab floor (like OpenVINS' built-in simulator): they stand
in for robots, worlds and networks so that tests, benchmarks and experiments can drive the
services' code without datasets or hardware. Services never import this package; it imports
``common`` and ``services`` and never the experiments (``lab``) or the command line
(``recslam``).

- :mod:`sim.cloud`: a room of landmarks and robots flying through it, as keyframes and map
  points for the cloud's atlas, or coded as an edge sends them.
- :mod:`sim.vio`: tracks and IMU without images, with ground truth, for the edge's VIO.
- :mod:`sim.robot`: a simulated robot, :mod:`sim.vio`'s tracks coded by the robot's own
  ``FrameCoder`` and played to an edge over the real transport.
- :mod:`sim.faultproxy`: a fault-injecting, throttling TCP proxy.
- :mod:`sim.netem`: bandwidth shaping between private network namespaces (``tbf``).

The EuRoC camera is one preset, the synthetic generator's
(:data:`common.data.synth.cameras.EUROC_CAM0` on ``T_IMU_CAM``); the simulators derive their
calibrations from it.
"""

from __future__ import annotations

import logging

logging.getLogger(__name__).addHandler(logging.NullHandler())

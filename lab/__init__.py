"""Experiments over the whole system: they drive the code the services run
(:mod:`lab.run` starts the very services ``recslam demo`` starts) and turn the runs into
tables and plots. Services never import this package, and it never imports the command line
(``recslam``).

- :mod:`lab.run`: whole runs as processes (orchestration, sites, the run report).
- :mod:`lab.links`: ``recslam experiment links``, the bit budget of every link, raw vs coded
  wire (tables and plot in :mod:`lab.links_report`; :mod:`lab.links_run` drives the two).
  :mod:`lab.seeds` and :mod:`lab.scale` follow the same split (``*_report``, ``*_run``), so
  that each report imports what it reads and nothing imports back.
- :mod:`lab.table3`: ``recslam experiment table3``, the paper's Table 3 (MBP) from replays of
  a recorded uplink through the cloud's own core (tables and plot in
  :mod:`lab.table3_report`; the core driven on the replay's clock in
  :mod:`lab.replay_schedule`; loop-detection precision / recall in :mod:`lab.loop_scoring`).
- :mod:`lab.vio_replay`: the robot front end, codecs and edge decoding of a sequence replayed
  in process into the edge's VIO, with ATE (``benchmarks/bench_vio_pipeline.py``).
- :mod:`lab.datasets`: where the development datasets are (the shared EuRoC excerpt).
"""

from __future__ import annotations

import logging

logging.getLogger(__name__).addHandler(logging.NullHandler())

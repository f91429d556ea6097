"""Experiments over the whole system: they drive the code the services run
(``recslam.orchestration`` starts the very services ``recslam demo`` starts) and turn the
runs into tables and plots. Services never import this package.

- :mod:`lab.links`: ``recslam experiment links``, the bit budget of every link, raw vs coded
  wire (tables and plot in :mod:`lab.links_report`).
- :mod:`lab.datasets`: where the development datasets are (the shared EuRoC excerpt).
"""

from __future__ import annotations

import logging

logging.getLogger(__name__).addHandler(logging.NullHandler())

"""dashboard tier: the viser web viewer of the fused map and its panels.

Reads the cloud's map only through :mod:`common.map_view` (``MapSource``); never imports
``services``. Entry point: :class:`dashboard.viewer.Dashboard`.
"""

import logging

logging.getLogger(__name__).addHandler(logging.NullHandler())

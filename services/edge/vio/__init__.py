"""Per-robot monocular-inertial VIO of the edge (paper Section VI.A), no network imports.

Front object: :class:`services.edge.vio.manager.VioManager`.
"""

import logging

logging.getLogger(__name__).addHandler(logging.NullHandler())

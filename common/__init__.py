"""Code shared by every tier: data, geometry, evaluation, protocol, codec.

``common`` imports none of ``services`` or ``dashboard``.
"""

import logging

logging.getLogger(__name__).addHandler(logging.NullHandler())

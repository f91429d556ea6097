"""Stream track numbers: names of a robot's tracks computable from its decoded stream alone.

The robot's tracker ids are never sent. Both ends number tracks from the decoded feature
stream (:func:`next_stream_numbers`): starting at 0, in codec order, a keyframe feature with a
link inherits the number of the previous track it continues and one without gets the next
unused number; a non-keyframe's survivors keep theirs and its new tracks get the next numbers.
The robot (``services.robot.coding``) maps numbers back to its tracker ids; the edge uses them
as ``FrameObservation.track_ids`` and in ``InertialFeedback.track_ids``.
"""

from __future__ import annotations

import numpy as np

from common.codec.types import KeyframeFeatures, NonKeyframeFeatures


def next_stream_numbers(
    previous: np.ndarray, next_number: int, features: KeyframeFeatures | NonKeyframeFeatures
) -> tuple[np.ndarray, int]:
    """Stream track numbers (N,) int64 of a decoded frame's rows and the next unused number,
    from the previous frame's numbers (P,) (see the module docstring). Pure: both ends run
    the same rule on the same decoded data."""
    previous = np.asarray(previous, dtype=np.int64)
    if isinstance(features, KeyframeFeatures):
        links = features.links.astype(np.int64)
        out = np.empty(len(links), np.int64)
        fresh = links < 0
        out[~fresh] = previous[links[~fresh]]
        n_new = int(fresh.sum())
    else:
        survivors = previous[features.survived]
        n_new = len(features) - len(survivors)
        out = np.empty(len(features), np.int64)
        out[: len(survivors)] = survivors
        fresh = np.zeros(len(features), bool)
        fresh[len(survivors) :] = True
    out[fresh] = np.arange(next_number, next_number + n_new, dtype=np.int64)
    out.setflags(write=False)
    return out, next_number + n_new

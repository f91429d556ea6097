"""The frame of an edge's payload: its poses and positions placed through its anchor.

The cloud holds each agent's map in its own frame: a keyframe pose ``T_world_body`` from the
edge lands at ``T_map_agent @ T_world_body``. That is right only while the edge's frame and the
cloud's agree, and they do not while a correction is on its way: the edge keeps sending in the
frame before it until it applies it, and applies it to what it has then. Without more, the
keyframes and points of those messages land where the correction took them from, and stay there
until local BA moves them enough to be sent again (the edge does not re-send what a correction
moved). After a loop, corrections move the newest keyframes most, exactly the ones the edge is
still refining and sending.

The coded payloads name their frame with a :class:`~common.links.edge_cloud_payloads.FrameAnchor`: a
keyframe the cloud has, at the pose the edge has for it in that frame. The payload then lands
at ``T_map_anchor @ inv(T_world_body_anchor) @ T_world_body``, i.e. with the correction
``T_fix = T_agent_anchor(cloud) @ inv(T_world_body_anchor)`` (in the agent's frame) applied
first; ``T_fix`` is the identity when the two agree. A payload without an anchor (the raw wire,
older recordings, the first keyframes of a map), or whose anchor the cloud no longer has (MBP
pruned it), lands as before.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from common.geometry import inverse_T, so3_log
from common.links.edge_cloud_payloads import FrameAnchor
from services.cloud.atlas.atlas import Atlas
from services.cloud.atlas.map_types import make_key
from services.cloud.fusion.uplink import DecodedKeyframe

MOVED_M = 1e-3
"""A payload counts as moved by its anchor (``FrameRebase.moved``) beyond 1 mm ..."""
MOVED_RAD = 1e-3
"""... or 1 mrad (about the edge's own thresholds for re-sending a keyframe)."""


@dataclass
class FrameRebase:
    """Places payloads through their anchors (see the module docstring) and counts them:
    ``anchored`` payloads with an anchor the cloud has, ``missing`` with one it does not,
    ``unanchored`` with none; ``moved`` of the anchored ones moved beyond
    :data:`MOVED_M` / :data:`MOVED_RAD`, by at most ``max_m`` / ``max_rad``."""

    anchored: int = 0
    missing: int = 0
    unanchored: int = 0
    moved: int = 0
    max_m: float = 0.0
    max_rad: float = 0.0

    def correction(
        self, atlas: Atlas, agent_id: int, anchor: FrameAnchor | None
    ) -> np.ndarray | None:
        """``T_fix`` (4, 4) for a payload of ``agent_id`` in the frame of ``anchor``, from the
        atlas' current poses (None: the payload lands through ``T_map_agent`` alone)."""
        if anchor is None:
            self.unanchored += 1
            return None
        key = make_key(agent_id, anchor.keyframe_id)
        if not atlas.has_keyframe(key):
            self.missing += 1
            return None
        self.anchored += 1
        T_agent_anchor = inverse_T(atlas.T_map_agent(agent_id)) @ atlas.T_map_body(key)
        T_fix = T_agent_anchor @ inverse_T(anchor.T_world_body)
        dt = float(np.linalg.norm(T_fix[:3, 3]))
        dr = float(np.linalg.norm(so3_log(T_fix[:3, :3])))
        if dt > MOVED_M or dr > MOVED_RAD:
            self.moved += 1
        self.max_m, self.max_rad = max(self.max_m, dt), max(self.max_rad, dr)
        return T_fix

    def summary(self) -> dict[str, float]:
        return {
            "anchored": self.anchored,
            "missing": self.missing,
            "unanchored": self.unanchored,
            "moved": self.moved,
            "max_m": self.max_m,
            "max_rad": self.max_rad,
        }


def rebased_keyframe(d: DecodedKeyframe, T_fix: np.ndarray) -> DecodedKeyframe:
    """``d`` with ``T_fix`` (4, 4) applied on the left of its pose, and its rotation applied to
    its velocity (biases are in the body frame: unchanged)."""
    T = T_fix @ d.T_world_body
    v = T_fix[:3, :3] @ d.velocity
    kf = d.keyframe
    if kf is not None:
        kf = dataclasses.replace(kf, T_world_body=T, velocity=v)
    return dataclasses.replace(d, T_world_body=T, velocity=v, keyframe=kf)

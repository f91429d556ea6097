"""The 3D scene: applies map deltas to a viser scene incrementally.

Nodes (``/map/...``): per agent point chunks (``points/a{agent}/c{serial}/kept`` and
``/pruned``), trajectory line segments (all keyframes, and kept-only for the MBP view),
subsampled keyframe frustums drawn as line segments, current pose axes with a label, ground
truth; ``/map/links/loops`` and ``/map/links/merges``. Points are coloured by agent.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import viser

from common.geometry import R_to_quat_wxyz
from common.map_view import GroundTruth, MapDelta
from dashboard.map_state import KeyframeTracks, PointChunks
from dashboard.panels import agent_label

log = logging.getLogger(__name__)

AGENT_COLORS: tuple[tuple[int, int, int], ...] = (
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (23, 190, 207),
)
LOOP_COLOR = (230, 200, 0)
MERGE_COLOR = (200, 0, 200)


def agent_color(agent: int) -> tuple[int, int, int]:
    """RGB colour of an agent (cycles through :data:`AGENT_COLORS`)."""
    return AGENT_COLORS[agent % len(AGENT_COLORS)]


def _paler(color: tuple[int, int, int], keep: float) -> tuple[int, int, int]:
    """``color`` mixed with white: ``keep`` of the colour, the rest white."""
    r, g, b = (int(keep * c + (1.0 - keep) * 255) for c in color)
    return r, g, b


@dataclass(frozen=True)
class SceneConfig:
    """Look of the scene.

    point_size_m: point size in metres; chunk_points: points per sealed chunk node;
    max_points: points kept at most; frustum_every: draw one frustum per this many keyframes;
    frustum_scale_m: frustum depth; line_width_px: trajectory / link width in pixels;
    track_hz: how often at most an agent's trajectory and frustums are resent while it grows.
    """

    point_size_m: float = 0.03
    chunk_points: int = 16_384
    max_points: int = 2_000_000
    frustum_every: int = 5
    frustum_scale_m: float = 0.15
    line_width_px: float = 2.0
    track_hz: float = 2.0


def frustum_segments(T_world_cam: np.ndarray, scale: float, aspect: float = 4 / 3) -> np.ndarray:
    """Wireframe of camera frustums: ``(K, 4, 4)`` poses -> ``(8K, 2, 3)`` segments (apex to
    four image corners at depth ``scale``, plus the image rectangle); camera looks along +z."""
    h = 0.5 * scale
    w = h * aspect
    c = np.array([[-w, -h, scale], [w, -h, scale], [w, h, scale], [-w, h, scale]])
    corners = np.einsum("kij,nj->kni", T_world_cam[:, :3, :3], c) + T_world_cam[:, None, :3, 3]
    apex = np.repeat(T_world_cam[:, None, :3, 3], 4, axis=1)
    spokes = np.stack([apex, corners], axis=2)  # (K, 4, 2, 3)
    rim = np.stack([corners, np.roll(corners, -1, axis=1)], axis=2)
    return np.concatenate([spokes, rim], axis=1).reshape(-1, 2, 3)


def _polyline(p: np.ndarray) -> np.ndarray:
    """(N, 3) positions -> (N-1, 2, 3) consecutive segments."""
    return np.stack([p[:-1], p[1:]], axis=1)


class MapScene:
    """Keeps a viser scene in step with a :class:`MapSource`'s deltas (call from one thread)."""

    def __init__(self, server: viser.ViserServer, config: SceneConfig) -> None:
        self._server = server
        self._cfg = config
        self.names: dict[int, str] = {}  # agent -> its robot's name (labels)
        self.points = PointChunks(config.chunk_points, config.max_points)
        self.keyframes = KeyframeTracks()
        self._handles: dict[str, object] = {}
        self._ground_truth: dict[int, GroundTruth] = {}
        self._loops = np.zeros((0, 2), np.int64)
        self._merges = np.zeros((0, 2), np.int64)
        self._links_dirty = False
        self._gt_dirty = False
        self._pending_tracks: set[int] = set()
        self._last_tracks = -np.inf
        self.mbp = False
        self.show_frustums = True
        self.show_ground_truth = True
        self.show_links = True
        server.scene.set_up_direction("+z")
        server.scene.add_grid("/grid", width=12, height=12, plane="xy", cell_size=1.0)

    @property
    def ground_truth(self) -> dict[int, GroundTruth]:
        return self._ground_truth

    # -------------------------------------------------------------- deltas

    def apply(self, delta: MapDelta, now: float = np.inf) -> None:
        """Take in one delta and send what changed (one atomic batch). ``now`` (s, monotonic)
        rate-limits trajectory resends to ``track_hz``; pending ones go out on a later call."""
        if delta.full:
            self.points.clear()
            self.keyframes.clear()
            for a in list(self._ground_truth):
                self._remove(f"/map/gt/a{a}")
            self._ground_truth = {}
        self.points.apply(delta.points, delta.removed_point_ids)
        self.keyframes.apply(delta.keyframes, delta.removed_keyframe_ids)
        if delta.ground_truth:
            self._ground_truth = {g.agent_id: g for g in delta.ground_truth}
            self._gt_dirty = True
        if delta.full or not (
            np.array_equal(delta.loops, self._loops) and np.array_equal(delta.merges, self._merges)
        ):
            self._loops, self._merges = delta.loops, delta.merges
            self._links_dirty = True
        with self._server.atomic():
            self._send_points()
            self._pending_tracks |= set(self.keyframes.take_dirty())
            due = now - self._last_tracks >= 1.0 / self._cfg.track_hz
            if self._pending_tracks and (due or delta.full):
                for a in sorted(self._pending_tracks):
                    self._send_track(a)
                self._pending_tracks.clear()
                self._last_tracks = now if np.isfinite(now) else self._last_tracks
                self._links_dirty = True
            if self._links_dirty:
                self._send_links()
            if self._gt_dirty:
                self._send_ground_truth()
            for a, T in delta.current_pose.items():
                self._send_pose(a, T)

    def _remove(self, name: str) -> None:
        h = self._handles.pop(name, None)
        if h is not None:
            h.remove()  # type: ignore[attr-defined]

    def _send_points(self) -> None:
        ops = self.points.take_ops()
        for a, s in ops.removals:
            self._remove(f"/map/points/a{a}/c{s}/kept")
            self._remove(f"/map/points/a{a}/c{s}/pruned")
        for up in ops.upserts:
            base = f"/map/points/a{up.agent}/c{up.serial}"
            for part, sel in (("kept", ~up.pruned), ("pruned", up.pruned)):
                name = f"{base}/{part}"
                if not np.any(sel):
                    self._remove(name)
                    continue
                self._handles[name] = self._server.scene.add_point_cloud(
                    name,
                    up.p_world[sel],
                    agent_color(up.agent),
                    point_size=self._cfg.point_size_m,
                    point_shape="square",
                    point_shading="flat",
                    visible=part == "kept" or not self.mbp,
                )

    def _lines(
        self, name: str, seg: np.ndarray, color: tuple[int, int, int], visible: bool
    ) -> None:
        if seg.shape[0] == 0:
            self._remove(name)
            return
        self._handles[name] = self._server.scene.add_line_segments(
            name,
            seg.astype(np.float32),
            color,
            thickness=self._cfg.line_width_px,
            thickness_units="screen",
            visible=visible,
        )

    def _send_track(self, agent: int) -> None:
        _, T, pruned = self.keyframes.track(agent)
        color = agent_color(agent)
        p = T[:, :3, 3]
        self._lines(f"/map/traj/a{agent}/all", _polyline(p), color, not self.mbp)
        self._lines(f"/map/traj/a{agent}/kept", _polyline(p[~pruned]), color, self.mbp)
        sub = np.zeros(T.shape[0], bool)
        sub[:: self._cfg.frustum_every] = True
        if T.shape[0]:
            sub[-1] = True
        dim = _paler(color, 0.5)
        for part, sel, vis in (
            ("kept", sub & ~pruned, True),
            ("pruned", sub & pruned, not self.mbp),
        ):
            seg = frustum_segments(T[sel], self._cfg.frustum_scale_m)
            self._lines(
                f"/map/frustums/a{agent}/{part}",
                seg,
                color if part == "kept" else dim,
                vis and self.show_frustums,
            )

    def _send_links(self) -> None:
        self._links_dirty = False
        for kind, pairs, color in (
            ("loops", self._loops, LOOP_COLOR),
            ("merges", self._merges, MERGE_COLOR),
        ):
            seg = []
            for a, b in pairs.tolist():
                pa, pb = self.keyframes.position(a), self.keyframes.position(b)
                if pa is not None and pb is not None:
                    seg.append((pa, pb))
            arr = np.array(seg, np.float64).reshape(-1, 2, 3)
            self._lines(f"/map/links/{kind}", arr, color, self.show_links)

    def _send_ground_truth(self) -> None:
        self._gt_dirty = False
        for a, g in self._ground_truth.items():
            pale = _paler(agent_color(a), 0.35)
            self._lines(f"/map/gt/a{a}", _polyline(g.p_world), pale, self.show_ground_truth)

    def set_names(self, names: dict[int, str]) -> None:
        """The agents' robot names (from the source's stats): labels drawn before a name was
        known are drawn again with it (a node added under the same name replaces it)."""
        for agent, text in names.items():
            if self.names.get(agent) == text:
                continue
            self.names[agent] = text
            if f"/map/pose/a{agent}" in self._handles:
                self._server.scene.add_label(f"/map/pose/a{agent}/label", text)

    def _send_pose(self, agent: int, T_world_body: np.ndarray) -> None:
        name = f"/map/pose/a{agent}"
        wxyz = R_to_quat_wxyz(T_world_body[:3, :3])
        pos = T_world_body[:3, 3]
        h = self._handles.get(name)
        if h is None:
            self._handles[name] = self._server.scene.add_frame(
                name, axes_length=0.3, axes_radius=0.02, wxyz=wxyz, position=pos
            )
            self._server.scene.add_label(f"{name}/label", agent_label(agent, self.names.get(agent)))
        else:
            h.wxyz = wxyz  # type: ignore[attr-defined]
            h.position = pos  # type: ignore[attr-defined]

    # -------------------------------------------------------------- toggles

    def set_mbp(self, on: bool) -> None:
        """Show the map with MBP (pruned points, keyframes and frustums hidden) or without."""
        self.mbp = on
        with self._server.atomic():
            for name, h in self._handles.items():
                if name.endswith("/pruned") or name.endswith("/all"):
                    vis = not on and (self.show_frustums or "/frustums/" not in name)
                    h.visible = vis  # type: ignore[attr-defined]
                elif name.startswith("/map/traj/") and name.endswith("/kept"):
                    h.visible = on  # type: ignore[attr-defined]

    def set_layer(self, prefix: str, visible: bool) -> None:
        """Show or hide frustums (``/map/frustums``), links or ground truth by name prefix."""
        with self._server.atomic():
            for name, h in self._handles.items():
                if name.startswith(prefix):
                    hide_pruned = self.mbp and name.endswith("/pruned")
                    h.visible = visible and not hide_pruned  # type: ignore[attr-defined]

    def node_names(self) -> list[str]:
        """Names of the scene nodes this object manages (for tests)."""
        return sorted(self._handles)

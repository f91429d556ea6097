"""The synthetic indoor scene: an axis-aligned room with axis-aligned boxes standing in it.

World frame: ``z`` up, origin at the centre of the floor. Every surface is an axis-aligned
rectangle (:class:`Face`) whose ``normal`` points to the side a camera can see it from
(into the room for the room's walls, out of the box for boxes). Face ``i`` of the scene has
index ``i`` in :attr:`Scene.faces`: the room's six faces first (``2 * axis + side``, side 0 the
low wall), then six per box in the same order (``6 + 6 * box + 2 * axis + side``, side 0 the
box's low face).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from common.errors import RecslamError


class SceneError(RecslamError):
    """Invalid room or box geometry."""


Vec3 = tuple[float, float, float]

# Tangent axes (u, v) of a face given its normal axis: walls are (horizontal, z).
_TANGENTS = {0: (1, 2), 1: (0, 2), 2: (0, 1)}


@dataclass(frozen=True)
class Box:
    """Axis-aligned box ``lo`` .. ``hi`` [m] in the world frame."""

    lo: Vec3
    hi: Vec3
    name: str = "box"

    def __post_init__(self) -> None:
        if not all(h > lo for lo, h in zip(self.lo, self.hi, strict=True)):
            raise SceneError(f"box {self.name}: hi {self.hi} must exceed lo {self.lo}")


@dataclass(frozen=True)
class Face:
    """One textured rectangle: normal along ``axis`` with sign ``normal_sign`` at coordinate
    ``offset``; it spans ``u_range`` on axis ``u_axis`` and ``v_range`` on ``v_axis``.

    Texture coordinates [m] of a point ``p`` on the face are
    ``s = (p[u_axis] - u_origin) * u_dir`` and ``t = (p[v_axis] - v_origin) * v_dir``,
    chosen so that walls read upright and unmirrored from the visible side.
    """

    axis: int
    normal_sign: int
    offset: float
    u_axis: int
    v_axis: int
    u_range: tuple[float, float]
    v_range: tuple[float, float]
    u_origin: float
    u_dir: float
    v_origin: float
    v_dir: float
    kind: str  # "floor", "ceiling", "wall", "box_top", "box_side", "box_bottom"
    name: str

    @property
    def size(self) -> tuple[float, float]:
        """(width along u, height along v) [m]."""
        return self.u_range[1] - self.u_range[0], self.v_range[1] - self.v_range[0]

    def texcoords(self, p: np.ndarray) -> np.ndarray:
        """Points (N, 3) on the face -> texture coordinates (N, 2) [m] in ``[0, size]``."""
        p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
        s = (p[:, self.u_axis] - self.u_origin) * self.u_dir
        t = (p[:, self.v_axis] - self.v_origin) * self.v_dir
        return np.stack([s, t], axis=1)

    def point(self, st: np.ndarray) -> np.ndarray:
        """Texture coordinates (N, 2) [m] -> world points (N, 3) on the face."""
        st = np.asarray(st, dtype=np.float64).reshape(-1, 2)
        p = np.empty((len(st), 3))
        p[:, self.axis] = self.offset
        p[:, self.u_axis] = self.u_origin + st[:, 0] * self.u_dir
        p[:, self.v_axis] = self.v_origin + st[:, 1] * self.v_dir
        return p


def _make_face(
    axis: int, normal_sign: int, offset: float, lo: Vec3, hi: Vec3, kind: str, name: str
) -> Face:
    ua, va = _TANGENTS[axis]
    u_range, v_range = (lo[ua], hi[ua]), (lo[va], hi[va])
    if axis == 2:
        # Floor/ceiling/box tops: s along +x, t along -y (as seen from above).
        u_origin, u_dir, v_origin, v_dir = u_range[0], 1.0, v_range[1], -1.0
    else:
        # Walls: t grows downwards from the top edge; s grows to the viewer's right, which
        # is z_up x normal (looking along -normal).
        right = np.cross([0.0, 0.0, 1.0], np.eye(3)[axis] * normal_sign)
        sgn = float(right[ua])
        u_origin = u_range[0] if sgn > 0 else u_range[1]
        u_dir, v_origin, v_dir = sgn, v_range[1], -1.0
    return Face(
        axis,
        normal_sign,
        float(offset),
        ua,
        va,
        u_range,
        v_range,
        float(u_origin),
        float(u_dir),
        float(v_origin),
        float(v_dir),
        kind,
        name,
    )


@dataclass(frozen=True)
class Scene:
    """Room ``room_lo`` .. ``room_hi`` [m] with ``boxes`` inside it (standing on the floor)."""

    room_lo: Vec3
    room_hi: Vec3
    boxes: tuple[Box, ...]
    faces: tuple[Face, ...] = field(init=False)

    def __post_init__(self) -> None:
        lo, hi = np.array(self.room_lo), np.array(self.room_hi)
        if not np.all(hi > lo):
            raise SceneError(f"room hi {self.room_hi} must exceed lo {self.room_lo}")
        for box in self.boxes:
            if np.any(np.array(box.lo) < lo) or np.any(np.array(box.hi) > hi):
                raise SceneError(f"box {box.name} {box.lo}..{box.hi} leaves the room")
        faces: list[Face] = []
        names = ("x", "y", "z")
        for axis in range(3):
            for side in (0, 1):
                offset = self.room_lo[axis] if side == 0 else self.room_hi[axis]
                kind = "wall" if axis < 2 else ("floor" if side == 0 else "ceiling")
                nsign = 1 if side == 0 else -1
                faces.append(
                    _make_face(
                        axis,
                        nsign,
                        offset,
                        self.room_lo,
                        self.room_hi,
                        kind,
                        f"room_{'lo' if side == 0 else 'hi'}{names[axis]}",
                    )
                )
        for box in self.boxes:
            for axis in range(3):
                for side in (0, 1):
                    offset = box.lo[axis] if side == 0 else box.hi[axis]
                    kind = "box_side" if axis < 2 else ("box_bottom" if side == 0 else "box_top")
                    nsign = -1 if side == 0 else 1
                    faces.append(
                        _make_face(
                            axis,
                            nsign,
                            offset,
                            box.lo,
                            box.hi,
                            kind,
                            f"{box.name}_{'lo' if side == 0 else 'hi'}{names[axis]}",
                        )
                    )
        object.__setattr__(self, "faces", tuple(faces))

    @property
    def size(self) -> np.ndarray:
        """(3,) room extent [m]."""
        return np.array(self.room_hi) - np.array(self.room_lo)

    def clearance(self, p: np.ndarray) -> np.ndarray:
        """Points (N, 3) -> distance [m] to the nearest surface; negative outside the room or
        inside a box."""
        p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
        lo, hi = np.array(self.room_lo), np.array(self.room_hi)
        d = np.minimum(p - lo, hi - p).min(axis=1)
        for box in self.boxes:
            blo, bhi = np.array(box.lo), np.array(box.hi)
            outside = np.maximum(np.maximum(blo - p, p - bhi), 0.0)
            dist = np.linalg.norm(outside, axis=1)
            inside = np.all((p > blo) & (p < bhi), axis=1)
            depth = np.minimum(p - blo, bhi - p).min(axis=1)
            d = np.minimum(d, np.where(inside, -depth, dist))
        return d

    def ray_cast(self, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Reference (unoptimised) ray caster: origin (3,), unit dirs (N, 3) ->
        (distance (N,) [m], face index (N,) int). The origin must be inside the room."""
        o = np.asarray(origin, dtype=np.float64).reshape(3)
        d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
        lo, hi = np.array(self.room_lo), np.array(self.room_hi)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / d
            tt = (np.where(d > 0, hi, lo) - o) * inv
        tt = np.where(np.isfinite(tt), tt, np.inf)
        axis = np.argmin(tt, axis=1)
        rows = np.arange(len(d))
        t = tt[rows, axis]
        face = 2 * axis + (d[rows, axis] > 0)
        for b, box in enumerate(self.boxes):
            with np.errstate(divide="ignore", invalid="ignore"):
                t1 = (np.array(box.lo) - o) * inv
                t2 = (np.array(box.hi) - o) * inv
            tn = np.where(np.isnan(t1), -np.inf, np.minimum(t1, t2))
            tf = np.where(np.isnan(t1), np.inf, np.maximum(t1, t2))
            tnear, tfar = tn.max(axis=1), tf.min(axis=1)
            hit = (tnear <= tfar) & (tnear > 0) & (tnear < t)
            ax = np.argmax(tn, axis=1)
            side = d[rows, ax] < 0  # ray going -axis hits the box's hi face
            t = np.where(hit, tnear, t)
            face = np.where(hit, 6 + 6 * b + 2 * ax + side, face)
        return t, face.astype(np.int64)


def vicon_room() -> Scene:
    """The default scene: an 8 x 7 x 3.5 m room (EuRoC's Vicon room size) with a low table
    in the middle, crates in the corners and a cabinet and a shelf against two walls."""
    boxes = (
        Box((-0.6, -0.4, 0.0), (0.6, 0.4, 0.75), "table"),
        Box((-4.0, -3.5, 0.0), (-3.1, -2.7, 1.1), "crate_a"),
        Box((3.0, -3.5, 0.0), (4.0, -2.5, 0.6), "crate_b"),
        Box((3.2, 2.6, 0.0), (4.0, 3.5, 1.6), "crate_c"),
        Box((-4.0, 2.9, 0.0), (-3.4, 3.5, 0.9), "crate_d"),
        Box((-4.0, -0.7, 0.0), (-3.55, 0.5, 2.1), "cabinet"),
        Box((0.3, 3.05, 0.0), (1.9, 3.5, 1.3), "shelf"),
        Box((3.1, -0.4, 0.0), (3.6, 0.4, 0.45), "step"),
    )
    return Scene((-4.0, -3.5, 0.0), (4.0, 3.5, 3.5), boxes)

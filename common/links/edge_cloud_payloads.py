"""The coded payloads of the edge <-> cloud link: keyframe states, map point ids, map points
and poses, each a sealed bit stream (:mod:`common.links.body`) that a message of
:mod:`common.links.edge_cloud` carries as ``bytes``. Pure functions over numpy arrays; no
message types here (they stay in ``edge_cloud``, which imports this module)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from common.codec.entropy import BitReader, BitWriter
from common.codec.errors import CodecError
from common.geometry import R_to_quat_wxyz, quat_wxyz_to_R
from common.links.body import (
    LinkDecodeError,
    get_scaled_geometric,
    get_scaled_signed,
    open_sealed,
    put_scaled_geometric,
    put_scaled_signed,
    seal,
)

STATE_VERSION = 2
"""2: an optional :class:`FrameAnchor` follows the rows (1, without one, still decodes)."""
POINTS_VERSION = 2
"""2: an optional :class:`FrameAnchor` follows the observation rows (1 still decodes)."""
POINT_IDS_VERSION = 1
POSITION_STEP_M = 1e-3
"""Map point positions travel on a 1 mm grid in the robot map's frame (error <= 0.5 mm per
axis); the keyframe states as float32."""
MAX_ITEMS = 1 << 22
"""Largest count of keyframes, points, features or rows one coded payload may declare."""
_STATE_COLS = 16


@dataclass(frozen=True, eq=False)
class FrameAnchor:
    """The frame of a payload's poses and positions, named by a keyframe the cloud has:
    ``T_world_body`` (4, 4) is the edge's pose of ``keyframe_id`` in it. A message may be in
    the frame before a correction the edge has not applied yet; the cloud places it through
    its own pose of the anchor (``services.cloud.fusion.rebase``; COVINS' ``pos_ref`` idea)."""

    keyframe_id: int
    T_world_body: np.ndarray


@dataclass(frozen=True, eq=False)
class KeyframeStates:
    """States of K keyframes: ``keyframe_ids`` (K,) int64, ``T_world_body`` (K, 4, 4),
    ``velocity_world`` (K, 3) m/s, ``bias_gyro`` (K, 3) rad/s, ``bias_accel`` (K, 3) m/s²;
    ``anchor``: their frame (None: the agent's map frame as the cloud has it)."""

    keyframe_ids: np.ndarray
    T_world_body: np.ndarray
    velocity_world: np.ndarray
    bias_gyro: np.ndarray
    bias_accel: np.ndarray
    anchor: FrameAnchor | None = None

    def __len__(self) -> int:
        return int(self.keyframe_ids.shape[0])


@dataclass(frozen=True, eq=False)
class PointBatch:
    """Map points of one message: ``ids`` (P,) int64 ascending, ``p_world`` (P, 3) m and the
    observation rows ``observations`` (R, 3) int64 ``[point id, keyframe id, feature index]``
    sorted by keyframe id and feature index (every row's point is in ``ids``); ``anchor``:
    the frame of ``p_world`` (see :class:`KeyframeStates`)."""

    ids: np.ndarray
    p_world: np.ndarray
    observations: np.ndarray
    anchor: FrameAnchor | None = None


@contextlib.contextmanager
def _decoding(what: str) -> Iterator[None]:
    """Entropy-decoder failures and impossible values as LinkDecodeError naming ``what``."""
    try:
        yield
    except (CodecError, ValueError, OverflowError) as exc:
        raise LinkDecodeError(f"{what}: {exc}") from exc


def _put_ids(w: BitWriter, ids: np.ndarray) -> None:
    """Distinct ascending non-negative ids: count, first, gaps - 1 (geometric)."""
    w.put_count(len(ids), "id")
    if len(ids):
        w.put_count(int(ids[0]), "id")
        put_scaled_geometric(w, np.diff(ids) - 1, "id")


def _get_ids(r: BitReader, what: str) -> np.ndarray:
    n = r.get_count(MAX_ITEMS)
    if n == 0:
        return np.zeros(0, np.int64)
    first = r.get_count(2**62)
    ids = first + np.concatenate([[0], np.cumsum(get_scaled_geometric(r, n - 1) + 1)])
    if ids[-1] >= 2**62:
        raise LinkDecodeError(f"{what}: id out of range")
    return ids.astype(np.int64)


def _put_anchor(w: BitWriter, anchor: FrameAnchor | None) -> None:
    """A flag, then the anchor's keyframe id and its pose as 7 float32 (position, wxyz)."""
    w.put_count(0 if anchor is None else 1, "anchor")
    if anchor is not None:
        if anchor.keyframe_id < 0:
            raise ValueError("anchor keyframe id must be >= 0")
        T = np.asarray(anchor.T_world_body, np.float64).reshape(4, 4)
        if not np.all(np.isfinite(T)):
            raise ValueError("anchor pose is not finite")
        row = np.concatenate([T[:3, 3], R_to_quat_wxyz(T[None, :3, :3]).reshape(4)])
        w.put_count(int(anchor.keyframe_id), "anchor")
        w.put_raw(np.ascontiguousarray(row, "<f4").view("<u4").astype(np.uint64), 32, "anchor")


def _get_anchor(r: BitReader, what: str) -> FrameAnchor | None:
    flag = r.get_count(1)
    if not flag:
        return None
    kf_id = r.get_count(2**62)
    row = r.get_raw(7, 32).astype("<u4").view("<f4").astype(np.float64)
    if not np.all(np.isfinite(row)):
        raise LinkDecodeError(f"{what}: non-finite anchor pose")
    T = np.eye(4)
    T[:3, :3] = quat_wxyz_to_R(row[None, 3:7])[0]
    T[:3, 3] = row[:3]
    return FrameAnchor(int(kf_id), T)


def encode_states(states: KeyframeStates) -> bytes:
    """Keyframe ids (ascending gaps, geometric), then per keyframe 16 float32: position (3),
    rotation as a unit quaternion wxyz (4), velocity (3), gyro bias (3), accel bias (3).

    Precision: float32 (position ~1 µm at 10 m, rotation ~1e-7 rad, velocity and biases 7
    significant digits); the decoder re-normalises the quaternion, so rotations stay exact
    rotations."""
    ids = np.asarray(states.keyframe_ids, np.int64).reshape(-1)
    order = np.argsort(ids, kind="stable")
    ids = ids[order]
    if len(ids) and (ids[0] < 0 or np.any(np.diff(ids) <= 0)):
        raise ValueError("keyframe ids must be distinct and >= 0")
    T = np.asarray(states.T_world_body, np.float64).reshape(-1, 4, 4)[order]
    cols = [
        T[:, :3, 3],
        R_to_quat_wxyz(T[:, :3, :3]).reshape(-1, 4),
        np.asarray(states.velocity_world, np.float64).reshape(-1, 3)[order],
        np.asarray(states.bias_gyro, np.float64).reshape(-1, 3)[order],
        np.asarray(states.bias_accel, np.float64).reshape(-1, 3)[order],
    ]
    rows = np.ascontiguousarray(np.concatenate(cols, axis=1), "<f4")
    w = BitWriter()
    _put_ids(w, ids)
    w.put_raw(rows.view("<u4").astype(np.uint64), 32, "state")
    _put_anchor(w, states.anchor)
    return seal(STATE_VERSION, w)


def decode_states(data: bytes, what: str = "keyframe states") -> KeyframeStates:
    """Inverse of :func:`encode_states`; LinkDecodeError on bad input."""
    r = open_sealed(data, (1, STATE_VERSION), what)
    with _decoding(what):
        ids = _get_ids(r, what)
        raw = r.get_raw(len(ids) * _STATE_COLS, 32).astype("<u4")
        anchor = _get_anchor(r, what) if data[0] >= 2 else None
    rows = raw.view("<f4").astype(np.float64).reshape(-1, _STATE_COLS)
    if not np.all(np.isfinite(rows)):
        raise LinkDecodeError(f"{what}: non-finite values")
    with _decoding(what):
        R = quat_wxyz_to_R(rows[:, 3:7]) if len(rows) else np.zeros((0, 3, 3))
    T = np.zeros((len(ids), 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = rows[:, :3]
    T[:, 3, 3] = 1.0
    return KeyframeStates(ids, T, rows[:, 7:10], rows[:, 10:13], rows[:, 13:16], anchor)


def encode_point_ids(map_point_ids: np.ndarray) -> bytes:
    """The map point of each of N features (-1: none): N, a has-point flag per feature
    (adaptive binary), then the ids of the features that have one, as signed differences to
    the previous such id (Laplace of a chosen scale)."""
    ids = np.asarray(map_point_ids, np.int64).reshape(-1)
    if np.any(ids < -1):
        raise ValueError("map point ids must be >= -1")
    has = ids >= 0
    w = BitWriter()
    w.put_count(len(ids), "side")
    w.put_flags(has, "flags", count_part="side")
    v = ids[has]
    if len(v):
        w.put_count(int(v[0]), "id")
        put_scaled_signed(w, np.diff(v), "id")
    return seal(POINT_IDS_VERSION, w)


def decode_point_ids(data: bytes, what: str = "map point ids") -> np.ndarray:
    """Inverse of :func:`encode_point_ids`: (N,) int64, -1 where a feature has no point."""
    r = open_sealed(data, POINT_IDS_VERSION, what)
    with _decoding(what):
        n = r.get_count(MAX_ITEMS)
        has = r.get_flags(n)
        out = np.full(n, -1, np.int64)
        k = int(has.sum())
        if k:
            first = r.get_count(2**62)
            out[has] = first + np.concatenate([[0], np.cumsum(get_scaled_signed(r, k - 1))])
    if np.any(out < -1):
        raise LinkDecodeError(f"{what}: negative map point id")
    return out


def encode_points(batch: PointBatch) -> bytes:
    """Points and observation rows (see :class:`PointBatch`; the arrays are sorted here).

    Layout: point ids (count, first, gaps); positions on the :data:`POSITION_STEP_M` grid, per
    axis as differences to the axis median (Laplace of a chosen scale); rows grouped by
    keyframe: the distinct keyframe ids (as point ids), rows per keyframe (geometric), feature
    index gaps within a keyframe (geometric) and each row's point as an index into the ids
    (uniform)."""
    ids = np.asarray(batch.ids, np.int64).reshape(-1)
    p = np.asarray(batch.p_world, np.float64).reshape(-1, 3)
    obs = np.asarray(batch.observations, np.int64).reshape(-1, 3)
    if len(ids) != len(p) or not np.all(np.isfinite(p)):
        raise ValueError(f"{len(ids)} point ids but {len(p)} positions (or non-finite)")
    order = np.argsort(ids, kind="stable")
    ids, p = ids[order], p[order]
    if len(ids) and (ids[0] < 0 or np.any(np.diff(ids) <= 0)):
        raise ValueError("point ids must be distinct and >= 0")
    obs = obs[np.lexsort((obs[:, 2], obs[:, 1]))]
    point_index = np.searchsorted(ids, obs[:, 0])
    named = point_index < len(ids)
    named[named] = ids[point_index[named]] == obs[named, 0]
    if len(obs) and (not named.all() or obs[:, 1:].min() < 0):
        raise ValueError("observation rows must name points of the batch and indices >= 0")
    w = BitWriter()
    _put_ids(w, ids)
    q = np.floor(p / POSITION_STEP_M + 0.5).astype(np.int64)
    for axis in range(3):
        centre = int(np.median(q[:, axis])) if len(q) else 0
        put_scaled_signed(w, np.array([centre]), "position")
        put_scaled_signed(w, q[:, axis] - centre, "position")
    kf_ids, per_kf = np.unique(obs[:, 1], return_counts=True)
    _put_ids(w, kf_ids)
    put_scaled_geometric(w, per_kf - 1, "rows")
    starts = (np.cumsum(per_kf) - per_kf).astype(np.int64)
    gaps = np.diff(obs[:, 2], prepend=0)
    gaps[starts] = obs[starts, 2]
    if np.any(gaps < 0):
        raise ValueError("duplicate observation rows")
    put_scaled_geometric(w, gaps, "feature")
    w.put_uniform(point_index, max(len(ids), 1), "point")
    _put_anchor(w, batch.anchor)
    return seal(POINTS_VERSION, w)


def decode_points(data: bytes, what: str = "map points") -> PointBatch:
    """Inverse of :func:`encode_points` (positions on the 1 mm grid); LinkDecodeError."""
    r = open_sealed(data, (1, POINTS_VERSION), what)
    with _decoding(what):
        ids = _get_ids(r, what)
        q = np.zeros((len(ids), 3), np.int64)
        for axis in range(3):
            centre = int(get_scaled_signed(r, 1)[0])
            q[:, axis] = centre + get_scaled_signed(r, len(ids))
        kf_ids = _get_ids(r, what)
        per_kf = get_scaled_geometric(r, len(kf_ids)) + 1
        n_rows = int(per_kf.sum())
        if n_rows > MAX_ITEMS:
            raise LinkDecodeError(f"{what}: {n_rows} observation rows exceed {MAX_ITEMS}")
        gaps = get_scaled_geometric(r, n_rows)
        point_index = r.get_uniform(n_rows, max(len(ids), 1))
        anchor = _get_anchor(r, what) if data[0] >= 2 else None
    if n_rows and (len(ids) == 0 or point_index.max() >= len(ids)):
        raise LinkDecodeError(f"{what}: observation names a point outside the batch")
    starts = (np.cumsum(per_kf) - per_kf).astype(np.int64)
    group = np.repeat(np.arange(len(kf_ids)), per_kf)
    feat = np.cumsum(gaps)
    feat -= np.repeat(feat[starts] - gaps[starts], per_kf) if n_rows else 0
    point_ids = ids[point_index] if n_rows else np.zeros(0, np.int64)
    obs = np.stack([point_ids, kf_ids[group], feat], axis=1).astype(np.int64).reshape(-1, 3)
    return PointBatch(ids, q * POSITION_STEP_M, obs, anchor)


POSES_VERSION = 1


def encode_poses(keyframe_ids: np.ndarray, T_world_body: np.ndarray) -> bytes:
    """Keyframe ids (ascending gaps) and per keyframe 7 float32: position (3) and rotation as a
    unit quaternion wxyz (4) (precision as :func:`encode_states`)."""
    ids = np.asarray(keyframe_ids, np.int64).reshape(-1)
    T = np.asarray(T_world_body, np.float64).reshape(-1, 4, 4)
    if len(ids) != len(T):
        raise ValueError(f"{len(ids)} keyframe ids but {len(T)} poses")
    order = np.argsort(ids, kind="stable")
    ids, T = ids[order], T[order]
    if len(ids) and (ids[0] < 0 or np.any(np.diff(ids) <= 0)):
        raise ValueError("keyframe ids must be distinct and >= 0")
    rows = np.concatenate([T[:, :3, 3], R_to_quat_wxyz(T[:, :3, :3]).reshape(-1, 4)], axis=1)
    w = BitWriter()
    _put_ids(w, ids)
    w.put_raw(np.ascontiguousarray(rows, "<f4").view("<u4").astype(np.uint64), 32, "pose")
    return seal(POSES_VERSION, w)


def decode_poses(data: bytes, what: str = "poses") -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`encode_poses`: (ids (N,) ascending, T_world_body (N, 4, 4))."""
    r = open_sealed(data, POSES_VERSION, what)
    with _decoding(what):
        ids = _get_ids(r, what)
        rows = r.get_raw(len(ids) * 7, 32).astype("<u4").view("<f4").astype(np.float64)
    rows = rows.reshape(-1, 7)
    if not np.all(np.isfinite(rows)):
        raise LinkDecodeError(f"{what}: non-finite values")
    T = np.tile(np.eye(4), (len(ids), 1, 1))
    with _decoding(what):
        if len(ids):
            T[:, :3, :3] = quat_wxyz_to_R(rows[:, 3:7])
    T[:, :3, 3] = rows[:, :3]
    return ids, T

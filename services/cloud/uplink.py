"""Edge <-> cloud messages as the cloud's domain inputs and outputs (no sockets, no state).

Decoding turns the wire messages of ``common.protocol.messages`` into the atlas' inputs:

- :class:`KeyframeUpdate` -> :class:`KeyframeInput`. The features are the keyframe coded
  *intra* by ``common.codec.frames`` with a fresh encoder state, so each one is decoded by a
  fresh :class:`FeatureDecoder`. Keypoints come back on the codec's level grid (level-0
  pixels via ``KeyframeFeatures.uv``); descriptors are lossless. The codec does not expose
  the word index it coded, but its encoder codes exactly ``Vocabulary.lookup(descriptor)``,
  so the same lookup on the decoded (identical) descriptors gives the coded words.
- :class:`MapPointUpdate` -> one :class:`MapPointInput` per point id.
- :class:`CullEvent` -> keyframe and map point ids.

Corrections for the edges are built by ``common.links.edge_cloud.encode_pose_correction``;
:func:`encode_keyframe_update` / :func:`encode_map_point_update` (and :func:`encode_session`, a
simulated session's every message) build what an edge sends
(tests, benchmarks and simulations use them as the edge's side of the link).

Everything that can be wrong in a peer's message raises :class:`UplinkError` naming the
message, the agent and the field.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from common.codec.errors import CodecError
from common.codec.frames import FeatureDecoder, FeatureEncoder
from common.codec.imu import ImuDecoder
from common.codec.types import CodecConfig, KeyframeFeatures
from common.errors import RecslamError
from common.links.edge_cloud import (
    CullEvent,
    KeyframePoses,
    KeyframeUpdate,
    KeyframeUpdateCoded,
    MapPointUpdate,
    MapPointUpdateCoded,
    decode_point_ids,
    decode_points,
    decode_states,
)
from common.protocol.arrays import pack_array, unpack_array
from common.protocol.errors import RemoteProtocolError
from common.vocabulary import Vocabulary
from services.cloud.atlas import AtlasError, KeyframeInput, MapPointInput

log = logging.getLogger(__name__)


class UplinkError(RecslamError):
    """A message from an edge that cannot be turned into the cloud's inputs."""


@dataclass(frozen=True, eq=False)
class DecodedKeyframe:
    """A :class:`KeyframeUpdate` in domain terms.

    ``keyframe`` is None for a pose-only update (empty features); then ``T_world_body``,
    ``velocity``, biases and ``map_point_ids`` (possibly empty) carry the new state.
    ``timestamp_ns`` is the exact sensor stamp; ``edge_map_id`` the edge's map of the robot.
    """

    agent_name: str
    edge_map_id: int
    keyframe_id: int
    timestamp_ns: int
    T_world_body: np.ndarray
    velocity: np.ndarray
    bias_gyro: np.ndarray
    bias_accel: np.ndarray
    map_point_ids: np.ndarray
    keyframe: KeyframeInput | None


def _one(data: bytes, shape: tuple[int, ...], what: str) -> np.ndarray:
    try:
        a = unpack_array(data, "<f8", shape, what)
    except RemoteProtocolError as exc:
        raise UplinkError(str(exc)) from exc
    if a.shape[0] != 1:
        raise UplinkError(f"{what}: expected one {list(shape)} array, got {a.shape[0]}")
    if not np.all(np.isfinite(a)):
        raise UplinkError(f"{what}: non-finite values")
    return a[0]


MAX_ORTHONORMALITY_ERROR = 1e-2
"""Largest ``|R^T R - I|`` entry of a pose's rotation that is repaired (projected onto SO(3));
the edge's pose updates after cloud corrections were seen off by more than 1e-5 in the demo,
and rejecting them made the edge reconnect and finally drop them. Beyond this the pose is
rejected as malformed."""


def _rigid(T: np.ndarray, what: str) -> np.ndarray:
    """``T (4, 4)`` with its rotation projected onto SO(3) (nearest rotation, SVD)."""
    R = T[:3, :3]
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    if err > MAX_ORTHONORMALITY_ERROR or np.linalg.det(R) <= 0:
        raise UplinkError(f"{what}: rotation is not orthonormal (|R^T R - I| = {err:.2g})")
    if err > 1e-9:
        U, _, Vt = np.linalg.svd(R)
        T = np.array(T, dtype=np.float64)
        T[:3, :3] = U @ Vt
        if err > 1e-5:
            log.debug("%s: re-orthonormalised a rotation off by %.2g", what, err)
    return T


def _vec(data: bytes, what: str) -> np.ndarray:
    if not data:
        return np.zeros(3)
    try:
        a = unpack_array(data, "<f8", (3,), what)
    except RemoteProtocolError as exc:
        raise UplinkError(str(exc)) from exc
    if a.shape[0] != 1 or not np.all(np.isfinite(a)):
        raise UplinkError(f"{what}: expected 3 finite float64 values")
    return a[0]


def _ids(data: bytes, what: str) -> np.ndarray:
    if not data:
        return np.zeros(0, np.int64)
    try:
        return unpack_array(data, "<i8", (), what)
    except RemoteProtocolError as exc:
        raise UplinkError(str(exc)) from exc


def decode_keyframe_update(
    msg: KeyframeUpdate | KeyframeUpdateCoded,
    agent_id: int,
    vocabulary: Vocabulary,
    codec: CodecConfig | None = None,
) -> DecodedKeyframe:
    """Decode one keyframe (schema-1 or coded); ``agent_id`` is the cloud's integer id of
    ``msg.agent_id``."""
    what = f"{type(msg).__name__} {msg.agent_id}/{msg.keyframe_id}"
    if msg.keyframe_id < 0:
        raise UplinkError(f"{what}: negative keyframe id")
    if isinstance(msg, KeyframeUpdateCoded):
        try:
            st = decode_states(msg.state, f"{what}: state")
            mp_ids = decode_point_ids(msg.map_point_ids, f"{what}: map_point_ids")
            if msg.imu:
                ImuDecoder().decode(msg.imu)
        except (RemoteProtocolError, CodecError) as exc:
            raise UplinkError(str(exc)) from exc
        if len(st) != 1 or int(st.keyframe_ids[0]) != msg.keyframe_id:
            raise UplinkError(f"{what}: state is not this keyframe's")
        T = st.T_world_body[0]
        vel, bg, ba = st.velocity_world[0], st.bias_gyro[0], st.bias_accel[0]
        if not msg.features:
            raise UplinkError(f"{what}: no features")
    else:
        T = _one(msg.T_world_body, (4, 4), f"{what}: T_world_body")
        T = _rigid(T, f"{what}: T_world_body")
        vel = _vec(msg.velocity_world, f"{what}: velocity_world")
        bg = _vec(msg.bias_gyro, f"{what}: bias_gyro")
        ba = _vec(msg.bias_accel, f"{what}: bias_accel")
        mp_ids = _ids(msg.map_point_ids, f"{what}: map_point_ids")
    kf = None
    if msg.features:
        cfg = codec or CodecConfig()
        try:
            feats = FeatureDecoder(vocabulary, cfg).decode(msg.features)
        except CodecError as exc:
            raise UplinkError(f"{what}: features: {exc}") from exc
        if not isinstance(feats, KeyframeFeatures):
            raise UplinkError(f"{what}: features are a non-keyframe payload")
        n = len(feats)
        if mp_ids.size == 0:
            mp_ids = np.full(n, -1, np.int64)
        if mp_ids.shape[0] != n:
            raise UplinkError(f"{what}: {mp_ids.shape[0]} map point ids for {n} features")
        words = vocabulary.lookup(feats.descriptors) if n else np.zeros(0, np.int32)
        try:
            kf = KeyframeInput(
                agent_id=agent_id,
                keyframe_id=msg.keyframe_id,
                timestamp=msg.timestamp_ns * 1e-9,
                T_world_body=T,
                keypoints=feats.uv(cfg),
                levels=feats.keypoints[:, 2],
                descriptors=feats.descriptors,
                word_ids=words,
                map_point_ids=mp_ids,
                velocity=vel,
                bias_gyro=bg,
                bias_accel=ba,
            )
        except AtlasError as exc:
            raise UplinkError(f"{what}: {exc}") from exc
    return DecodedKeyframe(
        msg.agent_id, msg.map_id, msg.keyframe_id, msg.timestamp_ns, T, vel, bg, ba, mp_ids, kf
    )


def decode_keyframe_poses(msg: KeyframePoses) -> list[DecodedKeyframe]:
    """The pose-only updates of a :class:`KeyframePoses` (``keyframe`` None in each)."""
    what = f"KeyframePoses of {msg.agent_id}"
    try:
        st = decode_states(msg.states, what)
    except RemoteProtocolError as exc:
        raise UplinkError(str(exc)) from exc
    none = np.zeros(0, np.int64)
    out = []
    for i, kf_id in enumerate(st.keyframe_ids.tolist()):
        vel, bg, ba = st.velocity_world[i], st.bias_gyro[i], st.bias_accel[i]
        out.append(
            DecodedKeyframe(
                msg.agent_id, msg.map_id, kf_id, 0, st.T_world_body[i], vel, bg, ba, none, None
            )
        )
    return out


def decode_map_point_update(
    msg: MapPointUpdate | MapPointUpdateCoded, agent_id: int
) -> list[MapPointInput]:
    """One :class:`MapPointInput` per id (observations grouped by map point id)."""
    what = f"{type(msg).__name__} of {msg.agent_id}"
    p: np.ndarray | None
    try:
        if isinstance(msg, MapPointUpdateCoded):
            batch = decode_points(msg.points, what)
            ids, p, obs = batch.ids, batch.p_world, batch.observations
        else:
            ids = _ids(msg.ids, f"{what}: ids")
            p = unpack_array(msg.p_world, "<f8", (3,), f"{what}: p_world") if msg.p_world else None
            obs = (
                unpack_array(msg.observations, "<i8", (3,), f"{what}: observations")
                if msg.observations
                else np.zeros((0, 3), np.int64)
            )
    except RemoteProtocolError as exc:
        raise UplinkError(str(exc)) from exc
    n = ids.shape[0]
    if p is None or p.shape[0] != n:
        raise UplinkError(f"{what}: {0 if p is None else p.shape[0]} positions for {n} ids")
    if np.unique(ids).size != n:
        raise UplinkError(f"{what}: duplicate map point ids")
    if obs.size and (obs.min() < 0):
        raise UplinkError(f"{what}: negative id or index in observations")
    order = np.argsort(obs[:, 0], kind="stable")
    obs = obs[order]
    starts = np.searchsorted(obs[:, 0], ids, side="left")
    ends = np.searchsorted(obs[:, 0], ids, side="right")
    if int((ends - starts).sum()) != obs.shape[0]:
        raise UplinkError(f"{what}: observations name map points not in ids")
    out = []
    for i in range(n):
        try:
            out.append(MapPointInput(agent_id, int(ids[i]), p[i], obs[starts[i] : ends[i], 1:3]))
        except AtlasError as exc:
            raise UplinkError(f"{what}: {exc}") from exc
    return out


def decode_cull_event(msg: CullEvent) -> tuple[np.ndarray, np.ndarray]:
    """(keyframe ids (K,), map point ids (M,)) int64 the edge removed."""
    what = f"CullEvent of {msg.agent_id}"
    kf = _ids(msg.keyframe_ids, f"{what}: keyframe_ids")
    mp = _ids(msg.map_point_ids, f"{what}: map_point_ids")
    if (kf.size and kf.min() < 0) or (mp.size and mp.min() < 0):
        raise UplinkError(f"{what}: negative ids")
    return kf, mp


# ----------------------------------------------------------------------------- edge side
def keyframe_features(
    keypoints: np.ndarray, levels: np.ndarray, descriptors: np.ndarray, codec: CodecConfig
) -> tuple[KeyframeFeatures, np.ndarray]:
    """Snap level-0 keypoints ``(N, 2)`` with ``levels (N,)`` to the codec grid and put them in
    canonical order; returns the features and ``order (N,)`` (feature i = input order[i])."""
    lev = np.asarray(levels, np.int64)
    s = codec.level_scale(lev)
    kp = np.zeros((lev.shape[0], 4), np.int32)
    xy = np.floor(np.asarray(keypoints, np.float64) / s[:, None] + 0.5)
    for level in np.unique(lev):
        w, h = codec.level_size(int(level))
        sel = lev == level
        xy[sel, 0] = np.clip(xy[sel, 0], 0, w - 1)
        xy[sel, 1] = np.clip(xy[sel, 1], 0, h - 1)
    kp[:, :2] = xy
    kp[:, 2] = lev
    raw = KeyframeFeatures(kp, descriptors, np.full(lev.shape[0], -1, np.int32))
    order = raw.canonical_order()
    return KeyframeFeatures(kp[order], raw.descriptors[order], raw.links[order]), order


def encode_keyframe_update(
    kf: KeyframeInput,
    agent_name: str,
    vocabulary: Vocabulary,
    edge_map_id: int = 0,
    previous_keyframe_id: int = -1,
    timestamp_ns: int | None = None,
    codec: CodecConfig | None = None,
) -> tuple[KeyframeUpdate, np.ndarray]:
    """What an edge sends for ``kf``: the message and ``order (N,)``, the coded order of the
    features (coded feature i is ``kf``'s feature ``order[i]``; map point observations must
    use coded indices)."""
    cfg = codec or CodecConfig()
    feats, order = keyframe_features(kf.keypoints, kf.levels, kf.descriptors, cfg)
    payload = FeatureEncoder(vocabulary, cfg).encode_keyframe(feats)
    ts = round(kf.timestamp * 1e9) if timestamp_ns is None else int(timestamp_ns)
    msg = KeyframeUpdate(
        agent_id=agent_name,
        map_id=edge_map_id,
        keyframe_id=kf.keyframe_id,
        previous_keyframe_id=previous_keyframe_id,
        timestamp_ns=ts,
        T_world_body=pack_array(kf.T_world_body, "<f8"),
        velocity_world=pack_array(kf.velocity, "<f8"),
        bias_gyro=pack_array(kf.bias_gyro, "<f8"),
        bias_accel=pack_array(kf.bias_accel, "<f8"),
        features=payload,
        map_point_ids=pack_array(kf.map_point_ids[order], "<i8"),
        imu=b"",
    )
    return msg, order


def encode_map_point_update(
    points: list[MapPointInput],
    agent_name: str,
    edge_map_id: int = 0,
    coded_index: dict[int, np.ndarray] | None = None,
) -> MapPointUpdate:
    """A MapPointUpdate of ``points``; ``coded_index {keyframe_id: inverse order (N,)}`` maps
    a keyframe's input feature index to its coded index (see :func:`encode_keyframe_update`)."""
    ids = np.array([p.map_point_id for p in points], np.int64)
    P = np.array([p.p_world for p in points], np.float64).reshape(-1, 3)
    rows = []
    for p in points:
        for kf_id, idx in p.observations.tolist():
            if coded_index is not None and kf_id in coded_index:
                idx = int(coded_index[kf_id][idx])
            rows.append((p.map_point_id, kf_id, idx))
    obs = np.array(rows, np.int64).reshape(-1, 3)
    return MapPointUpdate(
        agent_name,
        edge_map_id,
        pack_array(ids, "<i8"),
        pack_array(P, "<f8"),
        pack_array(obs, "<i8"),
    )


def encode_session(
    keyframes: list[KeyframeInput],
    map_points: list[MapPointInput],
    agent_name: str,
    vocabulary: Vocabulary,
    edge_map_id: int = 0,
) -> list[list[KeyframeUpdate | MapPointUpdate]]:
    """What an edge sends for one agent's session, per keyframe in order: its
    :class:`KeyframeUpdate`, then (if any) one :class:`MapPointUpdate` of the map points that
    keyframe observed first (the lowest keyframe id in a point's observations); observations
    in coded feature indices. For simulations (``services.cloud.simulation.make_session``),
    tests and benchmarks."""
    coded: dict[int, KeyframeUpdate] = {}
    inv: dict[int, np.ndarray] = {}
    for k in keyframes:  # every keyframe first: observations need the coded indices
        coded[k.keyframe_id], order = encode_keyframe_update(k, agent_name, vocabulary, edge_map_id)
        inv[k.keyframe_id] = np.argsort(order)
    first = {m.map_point_id: int(m.observations[:, 0].min()) for m in map_points}
    out: list[list[KeyframeUpdate | MapPointUpdate]] = []
    for k in keyframes:
        msgs: list[KeyframeUpdate | MapPointUpdate] = [coded[k.keyframe_id]]
        new = [m for m in map_points if first[m.map_point_id] == k.keyframe_id]
        if new:
            msgs.append(encode_map_point_update(new, agent_name, edge_map_id, coded_index=inv))
        out.append(msgs)
    return out

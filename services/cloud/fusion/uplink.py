"""Edge <-> cloud messages as the cloud's domain inputs and outputs (no sockets, no state).

Decoding turns the wire messages of ``common.protocol.messages`` into the atlas' inputs:

- :class:`KeyframeUpdate` -> :class:`KeyframeInput`. The features are the keyframe coded
  *intra* by ``common.codec.frames`` with a fresh encoder state, so each one is decoded from
  a fresh decoder's state: by a fresh :class:`FeatureDecoder`, or, with
  :class:`KeyframeDecoders`, by one decoder per codec config kept at that state
  (``FeatureDecoder.decode_detached``: no 8 MB of tables built and copied per keyframe).
  Keypoints come back on the codec's level grid (level-0 pixels via
  ``KeyframeFeatures.uv``); descriptors are lossless. The codec does not expose the word
  index it coded, but its encoder codes exactly ``Vocabulary.lookup(descriptor)``, so the
  same lookup on the decoded (identical) descriptors gives the coded words.
- :class:`MapPointUpdate` -> one :class:`MapPointInput` per point id.
- :class:`CullEvent` -> keyframe and map point ids.

Corrections for the edges are built by ``common.links.edge_cloud.encode_pose_correction``;
what an edge sends for a simulated session is built by ``sim.cloud``
(``encode_session``) with the links' own packers.

Everything that can be wrong in a peer's message raises :class:`UplinkError` naming the
message, the agent and the field.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from common.codec.errors import CodecError, CodecUsageError
from common.codec.frames import FeatureDecoder, fill_carried
from common.codec.imu import ImuDecoder
from common.codec.types import CodecConfig, ImuChunk, KeyframeFeatures, NonKeyframeFeatures
from common.errors import RecslamError
from common.geometry import transform_points
from common.links.edge_cloud import (
    CullEvent,
    KeyframePoses,
    KeyframeUpdate,
    KeyframeUpdateCoded,
    MapPointUpdate,
    MapPointUpdateCoded,
)
from common.links.edge_cloud_payloads import (
    FrameAnchor,
    decode_point_ids,
    decode_points,
    decode_states,
)
from common.protocol.arrays import unpack_array
from common.protocol.errors import RemoteProtocolError
from common.vocabulary import Vocabulary
from services.cloud.atlas.atlas import AtlasError, KeyframeInput, MapPointInput

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
    imu: ImuChunk | None = None
    """The IMU samples since the robot's previous uplinked keyframe (None: none sent)."""
    anchor: FrameAnchor | None = None
    """The frame of the pose (``services.cloud.fusion.rebase``; None: the agent's map frame)."""


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


class KeyframeDecoders:
    """One :class:`FeatureDecoder` per codec config, kept at a fresh decoder's state and
    reused for every keyframe coded with that config (``decode_detached``); decodes exactly
    what a fresh decoder would. Not thread-safe: one owner (the cloud's worker).

    A payload decoded elsewhere (the service's decode process, ``services.cloud.decode_pool``) is
    handed in with :meth:`offer` and taken by the next :meth:`decode` of the same bytes with
    the same config; anything else is decoded here."""

    def __init__(self, vocabulary: Vocabulary) -> None:
        self.vocabulary = vocabulary
        self._decoders: dict[CodecConfig, FeatureDecoder] = {}
        self._offered: dict[tuple[bytes, CodecConfig], KeyframeFeatures] = {}
        self.taken = 0  # offered decodes used

    def decode(self, payload: bytes, config: CodecConfig) -> KeyframeFeatures | NonKeyframeFeatures:
        done = self._offered.pop((payload, config), None)
        if done is not None:
            self.taken += 1
            return done
        decoder = self._decoders.get(config)
        if decoder is None:
            decoder = self._decoders[config] = FeatureDecoder(self.vocabulary, config)
        return decoder.decode_detached(payload)

    def offer(self, payload: bytes, config: CodecConfig, features: KeyframeFeatures) -> None:
        """``features`` decoded from ``payload`` with ``config`` (by this module's code)."""
        self._offered[(payload, config)] = features

    def forget(self) -> None:
        """Drop what was offered and not taken."""
        self._offered.clear()


def decode_keyframe_update(
    msg: KeyframeUpdate | KeyframeUpdateCoded,
    agent_id: int,
    vocabulary: Vocabulary,
    codec: CodecConfig | None = None,
    decoders: KeyframeDecoders | None = None,
    carried_from: Callable[[int], np.ndarray | None] | None = None,
) -> DecodedKeyframe:
    """Decode one keyframe (schema-1 or coded); ``agent_id`` is the cloud's integer id of
    ``msg.agent_id``; ``decoders`` (of ``vocabulary``): decode the features with those
    (default: a fresh decoder); ``carried_from(keyframe id)``: the descriptors (M, 32) of
    that keyframe of the same robot map as the cloud received them, or None, for features
    that carry the descriptor of a row of ``msg.previous_keyframe_id`` (UplinkError naming it
    if the cloud does not have it)."""
    what = f"{type(msg).__name__} {msg.agent_id}/{msg.keyframe_id}"
    if msg.keyframe_id < 0:
        raise UplinkError(f"{what}: negative keyframe id")
    anchor = None
    if isinstance(msg, KeyframeUpdateCoded):
        try:
            st = decode_states(msg.state, f"{what}: state")
            mp_ids = decode_point_ids(msg.map_point_ids, f"{what}: map_point_ids")
            imu = ImuDecoder().decode(msg.imu) if msg.imu else None
        except (RemoteProtocolError, CodecError) as exc:
            raise UplinkError(str(exc)) from exc
        if len(st) != 1 or int(st.keyframe_ids[0]) != msg.keyframe_id:
            raise UplinkError(f"{what}: state is not this keyframe's")
        T, anchor = st.T_world_body[0], st.anchor
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
        imu = _raw_imu(msg.imu, f"{what}: imu")
    kf = None
    if msg.features:
        cfg = codec or CodecConfig()
        try:
            if decoders is None:
                feats = FeatureDecoder(vocabulary, cfg).decode(msg.features)
            else:
                feats = decoders.decode(msg.features, cfg)
        except CodecError as exc:
            raise UplinkError(f"{what}: features: {exc}") from exc
        if not isinstance(feats, KeyframeFeatures):
            raise UplinkError(f"{what}: features are a non-keyframe payload")
        if (feats.links >= 0).any():  # descriptors carried from the previous keyframe
            prev_id = getattr(msg, "previous_keyframe_id", -1)
            prev = None if carried_from is None or prev_id < 0 else carried_from(prev_id)
            if prev is None:
                raise UplinkError(
                    f"{what}: features carry descriptors of keyframe {prev_id}, which the "
                    "cloud does not have"
                )
            try:
                feats = fill_carried(feats, prev)
            except CodecError as exc:
                raise UplinkError(f"{what}: features: {exc}") from exc
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
        msg.agent_id,
        msg.map_id,
        msg.keyframe_id,
        msg.timestamp_ns,
        T,
        vel,
        bg,
        ba,
        mp_ids,
        kf,
        imu,
        anchor,
    )


def _raw_imu(data: bytes, what: str) -> ImuChunk | None:
    """The schema-1 IMU rows "<f8 (M, 7)" [t_s, gyro xyz, accel xyz] (None: empty)."""
    if not data:
        return None
    try:
        rows = unpack_array(data, "<f8", (7,), what)
    except RemoteProtocolError as exc:
        raise UplinkError(str(exc)) from exc
    if not np.all(np.isfinite(rows)):
        raise UplinkError(f"{what}: non-finite IMU values")
    try:
        return ImuChunk(np.round(rows[:, 0] * 1e9).astype(np.int64), rows[:, 1:4], rows[:, 4:7])
    except CodecUsageError as exc:
        raise UplinkError(f"{what}: {exc}") from exc


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
                msg.agent_id,
                msg.map_id,
                kf_id,
                0,
                st.T_world_body[i],
                vel,
                bg,
                ba,
                none,
                None,
                anchor=st.anchor,
            )
        )
    return out


def decode_map_point_update(
    msg: MapPointUpdate | MapPointUpdateCoded,
    agent_id: int,
    frame: Callable[[FrameAnchor | None], np.ndarray | None] | None = None,
) -> list[MapPointInput]:
    """One :class:`MapPointInput` per id (observations grouped by map point id). ``frame``:
    the ``(4, 4)`` correction of a coded payload's frame, from its anchor
    (``services.cloud.fusion.rebase.FrameRebase.correction``; None: none)."""
    what = f"{type(msg).__name__} of {msg.agent_id}"
    p: np.ndarray | None
    try:
        if isinstance(msg, MapPointUpdateCoded):
            batch = decode_points(msg.points, what)
            ids, p, obs = batch.ids, batch.p_world, batch.observations
            T_fix = None if frame is None else frame(batch.anchor)
            if T_fix is not None:
                p = transform_points(T_fix, p)
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
    try:
        return MapPointInput.batch(agent_id, ids, p, obs[:, 1:3], starts, ends)
    except AtlasError as exc:
        raise UplinkError(f"{what}: {exc}") from exc


def decode_cull_event(msg: CullEvent) -> tuple[np.ndarray, np.ndarray]:
    """(keyframe ids (K,), map point ids (M,)) int64 the edge removed."""
    what = f"CullEvent of {msg.agent_id}"
    kf = _ids(msg.keyframe_ids, f"{what}: keyframe_ids")
    mp = _ids(msg.map_point_ids, f"{what}: map_point_ids")
    if (kf.size and kf.min() < 0) or (mp.size and mp.min() < 0):
        raise UplinkError(f"{what}: negative ids")
    return kf, mp

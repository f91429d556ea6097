"""Whole-frame feature coding: a sans-I/O encoder/decoder pair with explicit per-robot state.

Payload layout (little endian)::

    u8  magic 0xF5
    u8  version << 4 | kind        (kind 1 = keyframe, 2 = non-keyframe)
    u16 frame sequence number      (mod 2**16; the decoder rejects gaps)
    u16 vocabulary fingerprint     (low 16 bits of Vocabulary.fingerprint())
    ... range-coded body (whole 32-bit words)
    u32 CRC-32 of everything before it

Keyframe body: keypoints (see ``keypoints.py``), continuation links, descriptors (see
``descriptors.py``). Non-keyframe body: survival flags, predicted positions, new tracks.
A keyframe of kind 4 (:data:`KIND_KEYFRAME_CARRY`, ``CodecConfig.carry_track_descriptors``)
codes no descriptor for a feature that continues a track with one: it carries the track's.
A non-keyframe of kind 5 (:data:`KIND_NON_KEYFRAME_VELOCITY`, ``CodecConfig.track_velocity``)
may predict a track from its last step.

State both ends hold after every frame (:class:`FeatureCodecState`): the active tracks
(quarter-pixel positions, levels, last descriptor if any, last step if any), the adaptive
descriptor tables and
the adaptive flag counts. Encoder and decoder work on a copy and commit it only after a
frame was coded completely, so a rejected payload leaves the state untouched. The copy
shares the 8 MB descriptor tables, which keyframe coding updates in place while recording
the old values in an undo journal; a failure rolls them back (cheaper than copying them).
Code that keeps a reference to an older state object must not expect its tables to stay.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

import numpy as np

from common.codec import keypoints as kpc
from common.codec.descriptors import DescriptorCoder, DescriptorModelState, UndoLog, rollback
from common.codec.entropy import BitReader, BitWriter
from common.codec.errors import CodecError, CodecUsageError
from common.codec.types import CodecConfig, KeyframeFeatures, NonKeyframeFeatures
from common.vocabulary import Vocabulary

MAGIC = 0xF5
VERSION = 1
KIND_KEYFRAME = 1
KIND_NON_KEYFRAME = 2
KIND_STANDALONE_KEYFRAME = 3
"""A keyframe coded from a fresh state (:func:`encode_standalone_keyframe`): its descriptors
as one adaptive block, and no table update after it (nothing reads them), so it decodes in
one pass over the bit planes and leaves the decoder's tables untouched."""
KIND_NON_KEYFRAME_VELOCITY = 5
"""A non-keyframe whose survivors may be predicted by their track's last step
(``CodecConfig.track_velocity``, :func:`common.codec.keypoints.encode_non_keyframe`)."""
KIND_STANDALONE_CARRY = 6
"""A standalone keyframe some of whose features carry the descriptor of a row of the
receiver's previous keyframe (:func:`encode_standalone_keyframe` with ``carried``): their
rows are sent instead of their descriptors (the decoded ``links``; the descriptors are zero
until :func:`fill_carried`)."""
KIND_KEYFRAME_CARRY = 4
"""A keyframe whose features that continue a track with a descriptor say, one flag each,
whether they carry that descriptor (no bits for it; ``CodecConfig.carry_track_descriptors``;
the robot's tracker decides, ``FrontEndConfig.carry_max_hamming``); the others are coded as
in kind 1.
The edge's VIO keeps a map point's first descriptor and binds continued tracks by their link,
so what a continued feature's new descriptor would tell the edge is what the inter residual
paid for (~93 of ~170 bits per feature on EuRoC, ``codec.md``)."""
HEADER = struct.Struct("<BBHH")


@dataclass
class FeatureCodecState:
    """Per-robot state shared (identically) by encoder and decoder.

    tracks_q: (T, 2) int64 level-0 positions in 1/subpixel px. tracks_level: (T,) int64.
    tracks_desc: (T, 32) uint8 last descriptor; tracks_has_desc: (T,) bool.
    tracks_v: (T, 2) int64 the track's step in the last coded frame, 1/subpixel px;
    tracks_has_v: (T,) bool (False: new in that frame, or a keyframe's feature).
    """

    seq: int
    tracks_q: np.ndarray
    tracks_level: np.ndarray
    tracks_desc: np.ndarray
    tracks_has_desc: np.ndarray
    descriptors: DescriptorModelState
    survival_counts: np.ndarray
    link_counts: np.ndarray
    tracks_v: np.ndarray
    tracks_has_v: np.ndarray

    @classmethod
    def initial(cls, vocab: Vocabulary, config: CodecConfig) -> FeatureCodecState:
        return cls(
            seq=0,
            tracks_q=np.zeros((0, 2), np.int64),
            tracks_level=np.zeros(0, np.int64),
            tracks_desc=np.zeros((0, 32), np.uint8),
            tracks_has_desc=np.zeros(0, bool),
            descriptors=DescriptorModelState.initial(vocab, config.prior_weight),
            survival_counts=np.array([9.0, 10.0]),
            link_counts=np.array([1.0, 2.0, 1.0, 2.0]),
            tracks_v=np.zeros((0, 2), np.int64),
            tracks_has_v=np.zeros(0, bool),
        )

    def copy(self, descriptors: bool = True) -> FeatureCodecState:
        """Deep copy; ``descriptors=False`` shares the (large) descriptor tables, for
        non-keyframes, which never touch them."""
        return self._copy(self.descriptors.copy() if descriptors else self.descriptors)

    def copy_sharing_tables(self) -> FeatureCodecState:
        """Copy whose descriptor model shares the 8 MB count tables (everything else is
        copied): keyframe coding updates them in place with an undo journal instead."""
        return self._copy(self.descriptors.copy_counts())

    def _copy(self, descriptors: DescriptorModelState) -> FeatureCodecState:
        return FeatureCodecState(
            self.seq,
            self.tracks_q.copy(),
            self.tracks_level.copy(),
            self.tracks_desc.copy(),
            self.tracks_has_desc.copy(),
            descriptors,
            self.survival_counts.copy(),
            self.link_counts.copy(),
            self.tracks_v.copy(),
            self.tracks_has_v.copy(),
        )


def _previous_descriptors(
    st: FeatureCodecState, links: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The last descriptor (N, 32) uint8 of each keyframe feature's track and whether it
    has one (N,) bool, from the links (N,) (-1: a new track)."""
    links = np.asarray(links, np.int64)
    has_prev = np.zeros(len(links), dtype=bool)
    prev_desc = np.zeros((len(links), 32), np.uint8)
    linked = links >= 0
    has_prev[linked] = st.tracks_has_desc[links[linked]]
    prev_desc[linked] = st.tracks_desc[links[linked]]
    return prev_desc, has_prev


def _header(kind: int, seq: int, vocab_fp: int) -> bytes:
    return HEADER.pack(MAGIC, (VERSION << 4) | kind, seq & 0xFFFF, vocab_fp & 0xFFFF)


def _seal(head: bytes, body: bytes) -> bytes:
    payload = head + body
    return payload + struct.pack("<I", zlib.crc32(payload))


def _unseal(payload: bytes) -> bytes:
    """``payload`` without its CRC, which must match (CodecError otherwise)."""
    payload = bytes(payload)
    if len(payload) < HEADER.size + 4:
        raise CodecError(f"feature payload of {len(payload)} bytes is too short")
    (crc,) = struct.unpack("<I", payload[-4:])
    if zlib.crc32(payload[:-4]) != crc:
        raise CodecError("feature payload checksum mismatch (corrupted or truncated)")
    return payload[:-4]


class _Base:
    def __init__(self, vocabulary: Vocabulary, config: CodecConfig | None = None) -> None:
        config = CodecConfig() if config is None else config
        self.vocab = vocabulary
        self.config = config
        self.state = FeatureCodecState.initial(vocabulary, config)
        self._desc = DescriptorCoder(vocabulary, config.descriptor_block)
        self._vocab_fp = vocabulary.fingerprint() & 0xFFFF

    def _apply_keyframe(self, st: FeatureCodecState, kf: KeyframeFeatures) -> None:
        st.tracks_q = kpc.kf_track_q(kf.keypoints, self.config)
        st.tracks_level = kf.keypoints[:, 2].astype(np.int64)
        st.tracks_desc = kf.descriptors.copy()
        st.tracks_has_desc = np.ones(len(kf), dtype=bool)
        st.tracks_v = np.zeros((len(kf), 2), np.int64)
        st.tracks_has_v = np.zeros(len(kf), dtype=bool)

    @staticmethod
    def _apply_non_keyframe(
        st: FeatureCodecState, survived: np.ndarray, q: np.ndarray, levels: np.ndarray
    ) -> None:
        n_surv = int(survived.sum())
        n_new = q.shape[0] - n_surv
        st.tracks_v = np.concatenate(
            [q[:n_surv] - st.tracks_q[survived], np.zeros((n_new, 2), np.int64)]
        )
        st.tracks_has_v = np.concatenate([np.ones(n_surv, bool), np.zeros(n_new, bool)])
        st.tracks_q = q
        st.tracks_level = levels
        st.tracks_desc = np.concatenate([st.tracks_desc[survived], np.zeros((n_new, 32), np.uint8)])
        st.tracks_has_desc = np.concatenate(
            [st.tracks_has_desc[survived], np.zeros(n_new, dtype=bool)]
        )


class FeatureEncoder(_Base):
    """Robot side. ``encode_keyframe`` / ``encode_non_keyframe`` return payload bytes.

    ``last_bits`` holds the information content per part of the last payload
    (``keypoint``, ``link``, ``mode``, ``word``, ``residual``, ``survival``, ``new``, ``side``)
    and ``last_overhead_bits`` the framing (header, CRC, coder termination).
    """

    last_bits: dict[str, float]
    last_overhead_bits: float

    def _validate_keyframe(self, kf: KeyframeFeatures) -> None:
        cfg = self.config
        kp = kf.keypoints
        if len(kf) > cfg.max_features:
            raise CodecUsageError(f"{len(kf)} features exceed max_features={cfg.max_features}")
        if len(kf) == 0:
            return
        lev = kp[:, 2]
        if lev.min() < 0 or lev.max() >= cfg.n_levels:
            raise CodecUsageError(f"keypoint levels must be in [0, {cfg.n_levels})")
        if kp[:, 3].min() < 0 or kp[:, 3].max() >= cfg.angle_bins:
            raise CodecUsageError(f"angle bins must be in [0, {cfg.angle_bins})")
        for level in np.unique(lev):
            w, h = cfg.level_size(int(level))
            sel = kp[lev == level]
            if sel[:, :2].min() < 0 or sel[:, 0].max() >= w or sel[:, 1].max() >= h:
                raise CodecUsageError(f"keypoint outside the {w}x{h} image of level {level}")
        n_prev = self.state.tracks_q.shape[0]
        if kf.links.min() < -1 or kf.links.max() >= n_prev:
            raise CodecUsageError(f"links must be -1 or in [0, {n_prev}) (previous tracks)")
        if not kf.is_canonical():
            raise CodecUsageError(
                "keyframe features must be in canonical order: encode kf.canonical() and use "
                "that order on the robot too"
            )

    def encode_keyframe(self, kf: KeyframeFeatures, standalone: bool = False) -> bytes:
        """``standalone``: as :data:`KIND_STANDALONE_KEYFRAME` (the descriptor tables are
        left as they were)."""
        self._validate_keyframe(kf)
        st = self.state.copy_sharing_tables()
        undo: UndoLog = []
        try:
            return self._encode_keyframe(kf, st, undo, standalone)
        except BaseException:
            rollback(st.descriptors, undo)
            raise

    def _encode_keyframe(
        self, kf: KeyframeFeatures, st: FeatureCodecState, undo: UndoLog, standalone: bool
    ) -> bytes:
        w = BitWriter()
        kpc.encode_kf_keypoints(w, kf.keypoints, self.config)
        q = kpc.kf_track_q(kf.keypoints, self.config)
        kpc.encode_links(
            w,
            kf.links,
            q,
            kf.keypoints[:, 2].astype(np.int64),
            st.tracks_q,
            st.tracks_level,
            st.link_counts,
            self.config,
        )
        prev_desc, has_prev = _previous_descriptors(st, kf.links)
        # (a keyframe continuing no described track is coded as kind 1: the same body)
        carry = self.config.carry_track_descriptors and not standalone and bool(has_prev.any())
        if carry:
            same = has_prev & (kf.descriptors == prev_desc).all(axis=1)
            w.put_flags(same[has_prev], "mode")
            coded = ~same
            self._desc.encode(
                w, st.descriptors, kf.descriptors[coded], prev_desc[coded], has_prev[coded], undo
            )
        else:
            self._desc.encode(
                w, st.descriptors, kf.descriptors, prev_desc, has_prev, undo, standalone
            )
        self._apply_keyframe(st, kf)
        kind = KIND_STANDALONE_KEYFRAME if standalone else KIND_KEYFRAME
        return self._finish(st, w, KIND_KEYFRAME_CARRY if carry else kind)

    def encode_non_keyframe(self, nkf: NonKeyframeFeatures) -> bytes:
        cfg = self.config
        n_prev = self.state.tracks_q.shape[0]
        if nkf.survived.shape[0] != n_prev:
            raise CodecUsageError(
                f"survived has {nkf.survived.shape[0]} entries but there are {n_prev} tracks"
            )
        if len(nkf) > cfg.max_features:
            raise CodecUsageError(f"{len(nkf)} keypoints exceed max_features")
        kp = nkf.keypoints
        scaled = kp[:, :2] * cfg.subpixel
        if not np.all(np.isfinite(kp)) or not np.array_equal(scaled, np.round(scaled)):
            raise CodecUsageError(
                f"keypoints must lie on the 1/{cfg.subpixel} px grid (use quantise_uv)"
            )
        lev = kp[:, 2]
        if len(nkf) and (
            not np.array_equal(lev, np.round(lev)) or lev.min() < 0 or lev.max() >= cfg.n_levels
        ):
            raise CodecUsageError(f"levels must be integers in [0, {cfg.n_levels})")
        n_surv = int(nkf.survived.sum())
        w_img, h_img = cfg.image_width, cfg.image_height
        new = kp[n_surv:]
        if new.size and (
            new[:, :2].min() < 0 or new[:, 0].max() >= w_img or new[:, 1].max() >= h_img
        ):
            raise CodecUsageError(f"new keypoints must lie inside the {w_img}x{h_img} image")
        old = kp[:n_surv]
        if old.size and (
            old[:, 0].min() < -w_img
            or old[:, 0].max() >= 2 * w_img
            or old[:, 1].min() < -h_img
            or old[:, 1].max() >= 2 * h_img
        ):
            raise CodecUsageError("tracked keypoints far outside the image")
        st = self.state.copy(descriptors=False)
        w = BitWriter()
        steps = (st.tracks_v, st.tracks_has_v) if cfg.track_velocity else None
        kpc.encode_non_keyframe(
            w, nkf.survived, kp, st.tracks_q, st.tracks_level, st.survival_counts, cfg, steps
        )
        q = np.floor(kp[:, :2] * cfg.subpixel + 0.5).astype(np.int64)
        self._apply_non_keyframe(st, nkf.survived, q, lev.astype(np.int64))
        return self._finish(
            st, w, KIND_NON_KEYFRAME_VELOCITY if cfg.track_velocity else KIND_NON_KEYFRAME
        )

    def _finish(self, st: FeatureCodecState, w: BitWriter, kind: int) -> bytes:
        payload = _seal(_header(kind, st.seq, self._vocab_fp), w.finish())
        st.seq += 1
        self.state = st
        self.last_bits = dict(w.bits)
        self.last_overhead_bits = 8 * len(payload) - sum(w.bits.values())
        return payload


class FeatureDecoder(_Base):
    """Edge/cloud side: ``decode(payload)`` -> KeyframeFeatures | NonKeyframeFeatures."""

    def decode(self, payload: bytes) -> KeyframeFeatures | NonKeyframeFeatures:
        return self.decode_unchecked(_unseal(payload))

    def decode_detached(self, payload: bytes) -> KeyframeFeatures | NonKeyframeFeatures:
        """Decode ``payload`` as :meth:`decode` would, and leave this decoder's state as it
        was: the descriptor tables the keyframe updated in place are restored through the
        undo journal instead of being copied. One decoder so decodes any number of payloads
        that were each coded from the same state, e.g. the cloud's keyframes, each coded
        intra by a fresh encoder, without a fresh decoder's 8 MB tables per payload."""
        out, st, undo = self._decode(_unseal(payload))
        rollback(st.descriptors, undo)
        return out

    def decode_unchecked(self, framed: bytes) -> KeyframeFeatures | NonKeyframeFeatures:
        """Decode header + body without the CRC (used by robustness tests)."""
        out, self.state, _ = self._decode(framed)
        return out

    def _decode(
        self, framed: bytes
    ) -> tuple[KeyframeFeatures | NonKeyframeFeatures, FeatureCodecState, UndoLog]:
        """Decode header + body; the result, the state after it (its descriptor tables
        updated in place, as the undo journal records; not yet this decoder's state)."""
        if len(framed) < HEADER.size:
            raise CodecError("feature payload too short")
        magic, vk, seq, fp = HEADER.unpack(framed[: HEADER.size])
        if magic != MAGIC or vk >> 4 != VERSION:
            raise CodecError(f"not a feature payload (magic {magic:#x}, version {vk >> 4})")
        if fp != self._vocab_fp:
            raise CodecError("payload was coded with a different vocabulary")
        if seq != self.state.seq & 0xFFFF:
            raise CodecError(
                f"feature payload {seq} out of order (expected {self.state.seq & 0xFFFF})"
            )
        r = BitReader(framed[HEADER.size :])
        kind = vk & 0xF
        out: KeyframeFeatures | NonKeyframeFeatures
        undo: UndoLog = []
        if kind == KIND_STANDALONE_CARRY:
            out = self._decode_standalone_carry(r)
            return out, self.state, undo  # (a fresh state's tables, untouched)
        if kind in (KIND_KEYFRAME, KIND_STANDALONE_KEYFRAME, KIND_KEYFRAME_CARRY):
            st = self.state.copy_sharing_tables()
            try:
                out = self._decode_keyframe(
                    r, st, undo, kind == KIND_STANDALONE_KEYFRAME, kind == KIND_KEYFRAME_CARRY
                )
            except BaseException:
                rollback(st.descriptors, undo)
                raise
        elif kind in (KIND_NON_KEYFRAME, KIND_NON_KEYFRAME_VELOCITY):
            st = self.state.copy(descriptors=False)
            out = self._decode_non_keyframe(r, st, kind == KIND_NON_KEYFRAME_VELOCITY)
        else:
            raise CodecError(f"unknown frame kind {kind}")
        st.seq += 1
        return out, st, undo

    def _decode_keyframe(
        self,
        r: BitReader,
        st: FeatureCodecState,
        undo: UndoLog,
        standalone: bool = False,
        carry: bool = False,
    ) -> KeyframeFeatures:
        kp = kpc.decode_kf_keypoints(r, self.config)
        q = kpc.kf_track_q(kp, self.config)
        links = kpc.decode_links(
            r,
            kp.shape[0],
            q,
            kp[:, 2].astype(np.int64),
            st.tracks_q,
            st.tracks_level,
            st.link_counts,
            self.config,
        )
        prev_desc, has_prev = _previous_descriptors(st, links)
        if carry:
            same = np.zeros(len(links), dtype=bool)
            same[has_prev] = r.get_flags(int(has_prev.sum()))
            desc = prev_desc
            coded = ~same
            desc[coded] = self._desc.decode(
                r, st.descriptors, prev_desc[coded], has_prev[coded], undo
            )
        else:
            desc = self._desc.decode(r, st.descriptors, prev_desc, has_prev, undo, standalone)
        kf = KeyframeFeatures(kp, desc, links.astype(np.int32))
        self._apply_keyframe(st, kf)
        return kf

    def _decode_standalone_carry(self, r: BitReader) -> KeyframeFeatures:
        kp = kpc.decode_kf_keypoints(r, self.config)
        n = kp.shape[0]
        carried = kpc.decode_carried_rows(r, n)
        new = carried < 0
        desc = np.zeros((n, 32), np.uint8)
        none = np.zeros((int(new.sum()), 32), np.uint8)
        st = self.state.descriptors
        desc[new] = self._desc.decode(r, st, none, np.zeros(len(none), bool), None, True)
        return KeyframeFeatures(kp, desc, carried.astype(np.int32))

    def _decode_non_keyframe(
        self, r: BitReader, st: FeatureCodecState, velocity: bool = False
    ) -> NonKeyframeFeatures:
        cfg = self.config
        steps = (st.tracks_v, st.tracks_has_v) if velocity else None
        survived, q, levels = kpc.decode_non_keyframe(
            r, st.tracks_q, st.tracks_level, st.survival_counts, cfg, steps
        )
        if q.size and (
            q[:, 0].min() < -cfg.image_width * cfg.subpixel
            or q[:, 0].max() >= 2 * cfg.image_width * cfg.subpixel
            or q[:, 1].min() < -cfg.image_height * cfg.subpixel
            or q[:, 1].max() >= 2 * cfg.image_height * cfg.subpixel
        ):
            raise CodecError("decoded keypoint far outside the image")
        kp = np.concatenate([q / cfg.subpixel, levels[:, None].astype(np.float64)], axis=1)
        self._apply_non_keyframe(st, survived, q, levels)
        return NonKeyframeFeatures(survived, kp)


def encode_standalone_keyframe(
    vocabulary: Vocabulary,
    kf: KeyframeFeatures,
    config: CodecConfig | None = None,
    carried: np.ndarray | None = None,
) -> bytes:
    """A self-contained keyframe payload (fresh state, links dropped), e.g. edge -> cloud,
    where the receiver has not seen the robot's stream. Costs more than the stream's
    keyframes (the adaptive tables start from the vocabulary's prior). Kind
    :data:`KIND_STANDALONE_KEYFRAME`: the descriptors as one block, as many bits as 256-feature
    blocks within 0.3 % on the EuRoC excerpt (216.8 vs 217.5 bits per feature), decoded in
    one pass over the bit planes instead of one per block, without table updates.

    ``carried`` (N,) int: for each feature, the row of the receiver's previous keyframe whose
    descriptor equals its own, or -1. Those descriptors are not sent (kind
    :data:`KIND_STANDALONE_CARRY`, ~20 instead of ~200 bits a feature): the receiver decodes
    their rows as ``links`` and fills them in from the keyframe it has (:func:`fill_carried`).
    """
    enc = FeatureEncoder(vocabulary, config)
    plain = KeyframeFeatures(kf.keypoints, kf.descriptors, np.full(len(kf), -1, np.int32))
    rows = None if carried is None else np.asarray(carried, np.int64).reshape(-1)
    if rows is None or not (rows >= 0).any():
        return enc.encode_keyframe(plain, standalone=True)
    if len(rows) != len(kf):
        raise CodecUsageError(f"carried has {len(rows)} rows for {len(kf)} features")
    enc._validate_keyframe(plain)
    w = BitWriter()
    kpc.encode_kf_keypoints(w, kf.keypoints, enc.config)
    kpc.encode_carried_rows(w, rows)
    new = rows < 0
    none = np.zeros((int(new.sum()), 32), np.uint8)
    st = enc.state.descriptors
    enc._desc.encode(w, st, kf.descriptors[new], none, np.zeros(len(none), bool), None, True)
    return enc._finish(enc.state, w, KIND_STANDALONE_CARRY)


def fill_carried(kf: KeyframeFeatures, previous: np.ndarray) -> KeyframeFeatures:
    """A decoded standalone keyframe with the descriptors its features carry taken from the
    receiver's previous keyframe ``previous`` (M, 32) uint8 (its ``links`` name the rows),
    links cleared; CodecError if a row is not in ``previous``."""
    carried = kf.links >= 0
    if not carried.any():
        return kf
    rows = kf.links[carried].astype(np.int64)
    if rows.max() >= len(previous):
        raise CodecError(
            f"a feature carries row {int(rows.max())} of a keyframe of {len(previous)} features"
        )
    desc = kf.descriptors.copy()
    desc[carried] = previous[rows]
    return KeyframeFeatures(kf.keypoints, desc, np.full(len(kf), -1, np.int32))


def decode_standalone_keyframe(
    vocabulary: Vocabulary, payload: bytes, config: CodecConfig | None = None
) -> KeyframeFeatures:
    """Inverse of :func:`encode_standalone_keyframe`; raises CodecError on bad input."""
    out = FeatureDecoder(vocabulary, config).decode(payload)
    if not isinstance(out, KeyframeFeatures):
        raise CodecError("standalone payload is not a keyframe")
    return out

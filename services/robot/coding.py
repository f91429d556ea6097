"""From the front end's :class:`TrackedFrame` to the feature codec's payloads, bit-exact.

The tracker and the codec describe the same features in two data models; this module is the
adapter and checks on every frame that the two agree, so that what the edge decodes is exactly
what the robot's pipeline used:

- **Keyframe keypoint grid.** The codec carries keyframe keypoints on ORB's native integer
  grid of their pyramid level (``[x_l, y_l, l, angle_bin]``, level-0 position
  ``x_l * 1.2**l`` in float64). OpenCV reports ``x_l * 1.2**l`` in float32, which the tracker
  would snap to 1/4 px on its own; near a quarter-pixel boundary the two snaps can differ.
  :class:`CodecGridOrbExtractor` (installed into the front end by :func:`install_codec_grid`)
  therefore hands the tracker the codec's float64 level-0 positions, and orientations at the
  centre of their 32-bin sector. The tracker then continues from ``round(uv * 4) / 4``, which
  is exactly the codec's ``kf_track_q`` (no ties are possible: ``4 x 1.2**l`` is never an odd
  multiple of 1/2). Descriptors are computed at OpenCV's own positions (the same FAST
  corner), so they are unaffected.
- **Track order.** The tracker keeps a keyframe's features in ORB extraction order and
  non-keyframe survivors in that order; the codec sends keyframes in its canonical order and
  keeps survivors in *its* previous order. :class:`FrameCoder` keeps the codec's list of
  active track ids and maps the tracker's rows onto it by track id (ids are unique per frame),
  so ``survived`` and ``links`` refer to the codec's list.
- **IMU.** :func:`imu_used` snaps samples to the sensor lattice with
  :func:`common.codec.imu.dequantise_imu`; the robot feeds those values to its front end and
  the IMU codec reproduces them bit for bit (for EuRoC they are the CSV values unchanged).

**Stream track numbers** (how the edge names the robot's tracks, e.g. in
``InertialFeedback.track_ids``): the tracker's ids are never sent, so both ends number tracks
from the decoded stream alone (:func:`next_stream_numbers`): starting at 0, in codec order, a
keyframe feature with a link inherits the number of the previous track it continues and one
without gets the next unused number; a non-keyframe's survivors keep theirs and its new
tracks get the next numbers. :meth:`FrameCoder.tracker_ids_of` maps numbers back.

Every frame's mapping is verified (:class:`CodingMismatchError` otherwise): keyframe
``kf_track_q / 4`` equals the tracker's keypoints, levels agree, and every surviving track id
is found in the codec's list.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from common.codec import (
    CodecConfig,
    FeatureEncoder,
    ImuChunk,
    ImuEncoder,
    KeyframeFeatures,
    NonKeyframeFeatures,
    angle_to_bin,
)
from common.codec.imu import ImuCodecConfig, dequantise_imu
from common.codec.keypoints import kf_track_q
from common.codec.tracks import next_stream_numbers
from common.errors import RecslamError
from common.vocabulary import Vocabulary
from services.robot.config import FrontEndConfig, TrackingMode
from services.robot.orb_extractor import OrbExtractor, OrbFeatures
from services.robot.tracker import FrontEnd, TrackedFrame

logger = logging.getLogger(__name__)


class CodingMismatchError(RecslamError):
    """The tracker's output and the codec's data model disagree (a bug, never bad input)."""


def codec_config_for(front_end: FrontEndConfig, width: int, height: int) -> CodecConfig:
    """The codec options matching a front-end configuration and image size (px)."""
    if front_end.tracking is not TrackingMode.OPTICAL_FLOW:
        raise CodingMismatchError(
            "the robot codes optical-flow tracking only (ORB matching is a timing baseline)"
        )
    subpixel = 1.0 / front_end.quantisation_px
    if abs(subpixel - round(subpixel)) > 1e-12 or round(subpixel) < 1:
        raise CodingMismatchError(
            f"quantisation_px={front_end.quantisation_px} is not 1/n px for an integer n"
        )
    return CodecConfig(
        image_width=width,
        image_height=height,
        n_levels=front_end.orb.n_levels,
        scale_factor=front_end.orb.scale_factor,
        subpixel=round(subpixel),
        carry_track_descriptors=front_end.carry_track_descriptors,
    )


def snap_orb_features(feats: OrbFeatures, config: CodecConfig) -> OrbFeatures:
    """ORB features moved onto the codec's grid: level-0 keypoints ``x_l * scale**l`` (float64,
    the codec's expression) and angles at the centre of their orientation bin [deg]."""
    if len(feats) == 0:
        return feats
    kf = KeyframeFeatures.from_cv(_CvView(feats), feats.descriptors, None, config)
    bins = kf.keypoints[:, 3].astype(np.float64)
    angles = ((bins + 0.5) * (360.0 / config.angle_bins)).astype(np.float32)
    return OrbFeatures(
        keypoints=kf.uv(config),
        levels=feats.levels.copy(),
        angles=angles,
        responses=feats.responses,
        descriptors=feats.descriptors,
    )


class _CvKeypoint:
    __slots__ = ("angle", "octave", "pt")

    def __init__(self, pt: tuple[float, float], octave: int, angle: float) -> None:
        self.pt, self.octave, self.angle = pt, octave, angle


class _CvView(list):
    """OrbFeatures seen as a list of cv2.KeyPoint-like objects (for ``from_cv``)."""

    def __init__(self, feats: OrbFeatures) -> None:
        super().__init__(
            _CvKeypoint((float(p[0]), float(p[1])), int(lv), float(a))
            for p, lv, a in zip(feats.keypoints, feats.levels, feats.angles, strict=True)
        )


class CodecGridOrbExtractor:
    """An :class:`OrbExtractor` whose keypoints lie on the codec's grid (see module doc)."""

    def __init__(self, inner: OrbExtractor, config: CodecConfig) -> None:
        self.inner = inner
        self.config = inner.config
        self.codec_config = config

    @property
    def n_features(self) -> int:
        return self.inner.n_features

    @n_features.setter
    def n_features(self, n: int) -> None:
        self.inner.n_features = n

    def extract(
        self,
        image: np.ndarray,
        mask: np.ndarray | None = None,
        prefer_px: np.ndarray | None = None,
        prefer_radius_px: float = 0.0,
    ) -> OrbFeatures:
        feats = self.inner.extract(image, mask, prefer_px, prefer_radius_px)
        return snap_orb_features(feats, self.codec_config)


def install_codec_grid(front_end: FrontEnd, config: CodecConfig) -> None:
    """Make ``front_end`` extract keyframe ORB features on the codec's grid (idempotent)."""
    if not isinstance(front_end.orb, CodecGridOrbExtractor):
        front_end.orb = CodecGridOrbExtractor(front_end.orb, config)  # type: ignore[assignment]


def imu_used(
    timestamps_ns: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    config: ImuCodecConfig | None = None,
) -> ImuChunk:
    """IMU samples snapped to the sensor lattice: feed these to the front end and the codec.

    ``timestamps_ns`` (K,) int64; ``gyro`` (K, 3) rad/s; ``accel`` (K, 3) m/s².
    """
    return dequantise_imu(ImuChunk(timestamps_ns, gyro, accel), config)


@dataclass(frozen=True, eq=False)
class CodedFrame:
    """One frame as coded: ``payload`` (feature codec bytes), ``features`` (what the edge
    decodes: :class:`KeyframeFeatures` or :class:`NonKeyframeFeatures`, codec order) and
    ``track_ids`` (N,) int64, the tracker's track id of each row of ``features``;
    ``stream_ids`` (N,) int64, the stream track number of each row (what the edge computes)."""

    payload: bytes
    features: KeyframeFeatures | NonKeyframeFeatures
    track_ids: np.ndarray
    stream_ids: np.ndarray
    bits: dict[str, float]
    overhead_bits: float


class FrameCoder:
    """Robot side of the feature codec for one front end (stateful, frame by frame).

    ``encode(frame)`` sees the front end's :class:`TrackedFrame` in order; non-keyframes may
    be left out (the uplink's rate control and fresh-before-complete rule: see
    :mod:`services.robot.uplink_budget`). The next coded frame is then coded against the last
    coded one: its survivors are the tracks it shares with that frame, and a track born in a
    skipped frame is a new track of it (both ends number the stream from what was sent).
    ``links=False`` codes every keyframe on its own (no continuation links, so no inter
    coding of descriptors either): the all-frames intra baseline of the paper's [55].
    """

    def __init__(self, vocabulary: Vocabulary, config: CodecConfig, *, links: bool = True):
        self.config = config
        self.links = links
        self.encoder = FeatureEncoder(vocabulary, config)
        self.track_ids = np.zeros(0, np.int64)
        """Codec order of the active tracks (the tracker's ids)."""
        self.stream_ids = np.zeros(0, np.int64)
        """Stream track numbers of the active tracks (codec order)."""
        self.next_stream_id = 0
        self._frames = 0
        self._last_index: int | None = None  # the front end's index of the last coded frame

    def encode(self, frame: TrackedFrame) -> CodedFrame:
        """Code one frame; raises :class:`CodingMismatchError` if the models disagree."""
        features: KeyframeFeatures | NonKeyframeFeatures
        if frame.is_keyframe:
            kf_features, ids = self._keyframe(frame)
            payload = self.encoder.encode_keyframe(kf_features)
            features = kf_features
        else:
            nkf_features, ids = self._non_keyframe(frame)
            payload = self.encoder.encode_non_keyframe(nkf_features)
            features = nkf_features
        self.stream_ids, self.next_stream_id = next_stream_numbers(
            self.stream_ids, self.next_stream_id, features
        )
        self.track_ids = ids
        self._frames += 1
        self._last_index = frame.frame_index
        ids.setflags(write=False)
        return CodedFrame(
            payload,
            features,
            ids,
            self.stream_ids,
            dict(self.encoder.last_bits),
            self.encoder.last_overhead_bits,
        )

    def tracker_ids_of(self, stream_ids: np.ndarray) -> np.ndarray:
        """Tracker ids (M,) int64 of stream track numbers (M,); -1 for tracks no longer active."""
        stream_ids = np.asarray(stream_ids, dtype=np.int64).reshape(-1)
        out = np.full(len(stream_ids), -1, np.int64)
        if len(self.stream_ids) and len(stream_ids):
            order = np.argsort(self.stream_ids, kind="stable")
            srt = self.stream_ids[order]
            at = np.clip(np.searchsorted(srt, stream_ids), 0, len(srt) - 1)
            found = srt[at] == stream_ids
            out[found] = self.track_ids[order[at[found]]]
        return out

    def _positions(self, ids: np.ndarray) -> np.ndarray:
        """Rows of the codec's previous list for ``ids`` (-1 where absent)."""
        prev = self.track_ids
        if len(prev) == 0 or len(ids) == 0:
            return np.full(len(ids), -1, np.int64)
        order = np.argsort(prev, kind="stable")
        sorted_prev = prev[order]
        at = np.clip(np.searchsorted(sorted_prev, ids), 0, len(prev) - 1)
        found = sorted_prev[at] == ids
        return np.where(found, order[at], -1).astype(np.int64)

    def _check_unique(self, frame: TrackedFrame) -> None:
        if len(np.unique(frame.track_ids)) != len(frame):
            raise CodingMismatchError(f"frame {frame.frame_index}: duplicate track ids")

    def _keyframe(self, frame: TrackedFrame) -> tuple[KeyframeFeatures, np.ndarray]:
        cfg = self.config
        self._check_unique(frame)
        if frame.descriptors is None or frame.angles is None:
            raise CodingMismatchError(f"keyframe {frame.frame_index} has no descriptors")
        n = len(frame)
        levels = frame.levels.astype(np.int64)
        scale = cfg.level_scale(levels)
        kp = np.zeros((n, 4), np.int32)
        if n:
            # Exact: |uv_q / s - x_l| <= 1/8 (s >= 1), so rounding recovers ORB's integer pixel.
            kp[:, :2] = np.floor(frame.keypoints / scale[:, None] + 0.5).astype(np.int32)
            kp[:, 2] = levels
            kp[:, 3] = angle_to_bin(frame.angles.astype(np.float64), cfg.angle_bins)
            used_q = frame.keypoints * cfg.subpixel
            if not np.array_equal(kf_track_q(kp, cfg).astype(np.float64), used_q):
                bad = int(np.count_nonzero(np.any(kf_track_q(kp, cfg) != used_q, axis=1)))
                raise CodingMismatchError(
                    f"keyframe {frame.frame_index}: {bad} keypoints are not on the codec grid "
                    "(install_codec_grid() missing?)"
                )
        links = self._positions(frame.track_ids)
        if not self.links:
            links[:] = -1
        kf = KeyframeFeatures(kp, frame.descriptors, links.astype(np.int32))
        order = kf.canonical_order()
        coded = KeyframeFeatures(kf.keypoints[order], kf.descriptors[order], kf.links[order])
        return coded, frame.track_ids[order].astype(np.int64)

    def _non_keyframe(self, frame: TrackedFrame) -> tuple[NonKeyframeFeatures, np.ndarray]:
        self._check_unique(frame)
        rows_in_prev = self._positions(frame.track_ids)
        surv = np.flatnonzero(rows_in_prev >= 0)
        if self._last_index is not None and frame.frame_index == self._last_index + 1:
            # The previous frame was coded: the tracker's own survivors must be the codec's.
            n_prev_tracker = len(frame.survived_mask_vs_previous)
            if n_prev_tracker != len(self.track_ids):
                raise CodingMismatchError(
                    f"frame {frame.frame_index}: tracker had {n_prev_tracker} tracks, the codec "
                    f"{len(self.track_ids)}"
                )
            n_surv = int(frame.survived_mask_vs_previous.sum())
            if not np.array_equal(surv, np.arange(n_surv)):
                raise CodingMismatchError(
                    f"frame {frame.frame_index}: survivors and new tracks do not match the ids"
                )
        survived = np.zeros(len(self.track_ids), bool)
        survived[rows_in_prev[surv]] = True
        # Survivors in the codec's previous order, then new tracks in the tracker's order.
        surv_rows = surv[np.argsort(rows_in_prev[surv], kind="stable")]
        rows = np.concatenate([surv_rows, np.flatnonzero(rows_in_prev < 0)]).astype(np.int64)
        kp = np.concatenate(
            [frame.keypoints[rows], frame.levels[rows, None].astype(np.float64)], axis=1
        )
        return NonKeyframeFeatures(survived, kp), frame.track_ids[rows].astype(np.int64)


class ImuCoder:
    """Robot side of the IMU codec: ``encode(chunk) -> bytes`` (chunks in time order)."""

    def __init__(self, config: ImuCodecConfig | None = None) -> None:
        self.encoder = ImuEncoder(ImuCodecConfig() if config is None else config)

    def encode(self, chunk: ImuChunk) -> bytes:
        return self.encoder.encode(chunk)

"""What the feature codec carries: frozen dataclasses, quantisation grids and the config.

Quantisation (the robot snaps its own data to these grids *before* using it, so what the
edge decodes is exactly what the robot used):

- Keyframe keypoints live on ORB's native grid: integer pixel ``(x_l, y_l)`` in the image of
  pyramid level ``l`` (what OpenCV's FAST detects; ``kp.pt = (x_l, y_l) * 1.2**l``), the level
  ``l`` in ``[0, n_levels)`` and the orientation bin ``floor(angle / 360 * 32) mod 32``.
  Level-0 pixel coordinates are ``x_l * scale_factor**l`` (:meth:`KeyframeFeatures.uv`).
- Non-keyframe keypoints ``[u, v, l]``: level-0 pixel coordinates on a grid of
  ``1 / subpixel`` px (default 1/4 px: every value is a multiple of 0.25, exact in float64)
  and the pyramid level the track's feature was detected at.

Track identity is implicit in ordering. After every frame both ends hold the list of active
tracks: after a keyframe it is the keyframe's features in their (canonical) order; after a
non-keyframe it is the previous list's survivors in order followed by the new tracks.
``NonKeyframeFeatures.survived[i]`` refers to entry ``i`` of the previous list and
``KeyframeFeatures.links[n]`` names the previous list's entry that keyframe feature ``n``
continues (or -1).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from common.codec.errors import CodecUsageError


@dataclass(frozen=True)
class CodecConfig:
    """Codec options (both ends must agree).

    image_width, image_height: level-0 image size in px (EuRoC: 752 x 480).
    n_levels, scale_factor: ORB pyramid (8 levels, 1.2).
    angle_bins: orientation bins of keyframe keypoints (32).
    subpixel: non-keyframe grid is 1/subpixel px (4 -> 0.25 px).
    max_features: the decoder rejects frames announcing more features (16384).
    descriptor_block: features per adaptation block of the descriptor model (256).
    prior_weight: weight (in samples) of the vocabulary's bit prior (2.0).
    carry_track_descriptors: a keyframe feature that continues a track with a descriptor and
        has that very descriptor costs a flag and no descriptor bits (True; the receiver
        decodes either way, the payload's kind says which). False, and for the features
        whose descriptor differs: coded against it, intra or inter (XOR residual), whichever
        is cheaper: the paper's [55].
    track_velocity: a non-keyframe may predict each track from its last step plus an affine
        correction (kind 5; True) instead of by one affine flow for all (kind 2). The decoder
        reads either.
    """

    image_width: int = 752
    image_height: int = 480
    n_levels: int = 8
    scale_factor: float = 1.2
    angle_bins: int = 32
    subpixel: int = 4
    max_features: int = 16384
    descriptor_block: int = 256
    prior_weight: float = 2.0
    carry_track_descriptors: bool = True
    track_velocity: bool = True

    def level_scale(self, level: np.ndarray) -> np.ndarray:
        """``scale_factor ** level`` as float64 (same expression everywhere)."""
        return np.power(float(self.scale_factor), np.asarray(level, dtype=np.float64))

    def level_size(self, level: int) -> tuple[int, int]:
        """(width, height) of the level image: ``round(size / scale_factor**level)``."""
        s = float(self.scale_factor) ** level
        return int(np.floor(self.image_width / s + 0.5)), int(np.floor(self.image_height / s + 0.5))


def _as_array(
    x: np.ndarray, dtype: type[np.generic], shape_tail: tuple[int, ...], what: str
) -> np.ndarray:
    a = np.asarray(x)
    if a.ndim != 1 + len(shape_tail) or a.shape[1:] != shape_tail:
        want = ", ".join(["N", *map(str, shape_tail)])
        raise CodecUsageError(f"{what} must have shape ({want}), got {a.shape}")
    out = np.array(a, dtype=dtype, copy=True)
    out.setflags(write=False)
    return out


class CvKeypointLike(Protocol):
    """What :meth:`KeyframeFeatures.from_cv` reads of a keypoint (``cv2.KeyPoint`` has it)."""

    @property
    def pt(self) -> Sequence[float]: ...  # (x, y) level-0 pixels

    @property
    def octave(self) -> int: ...  # pyramid level in the low byte

    @property
    def angle(self) -> float: ...  # degrees


@dataclass(frozen=True)
class KeyframeFeatures:
    """ORB features of a keyframe.

    keypoints: (N, 4) int32 ``[x_l, y_l, l, angle_bin]`` (see module docstring).
    descriptors: (N, 32) uint8 ORB descriptors.
    links: (N,) int32 index into the previous frame's active tracks this feature continues,
        or -1 for a new track.
    """

    keypoints: np.ndarray
    descriptors: np.ndarray
    links: np.ndarray

    def __post_init__(self) -> None:
        kp = _as_array(self.keypoints, np.int32, (4,), "keypoints")
        de = _as_array(self.descriptors, np.uint8, (32,), "descriptors")
        if np.asarray(self.descriptors).dtype != np.uint8:
            raise CodecUsageError("descriptors must be uint8")
        li = np.array(np.asarray(self.links), dtype=np.int32).reshape(-1)
        li.setflags(write=False)
        if not (kp.shape[0] == de.shape[0] == li.shape[0]):
            raise CodecUsageError(
                f"keypoints ({kp.shape[0]}), descriptors ({de.shape[0]}) and links "
                f"({li.shape[0]}) must have the same length"
            )
        object.__setattr__(self, "keypoints", kp)
        object.__setattr__(self, "descriptors", de)
        object.__setattr__(self, "links", li)

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])

    def uv(self, config: CodecConfig = CodecConfig()) -> np.ndarray:
        """Level-0 pixel coordinates ``(N, 2) float64``."""
        s = config.level_scale(self.keypoints[:, 2])
        return self.keypoints[:, :2].astype(np.float64) * s[:, None]

    def canonical_order(self) -> np.ndarray:
        """Permutation sorting features by (level, y_l, x_l, angle, descriptor bytes)."""
        kp = self.keypoints
        keys = [self.descriptors[:, i] for i in range(31, -1, -1)]
        keys += [kp[:, 3], kp[:, 0], kp[:, 1], kp[:, 2]]
        return np.lexsort(keys)

    def canonical(self) -> KeyframeFeatures:
        """The same features in the codec's canonical order (the order the edge decodes)."""
        order = self.canonical_order()
        return KeyframeFeatures(self.keypoints[order], self.descriptors[order], self.links[order])

    def is_canonical(self) -> bool:
        return bool(np.array_equal(self.canonical_order(), np.arange(len(self))))

    def equals(self, other: KeyframeFeatures) -> bool:
        return (
            np.array_equal(self.keypoints, other.keypoints)
            and np.array_equal(self.descriptors, other.descriptors)
            and np.array_equal(self.links, other.links)
        )

    @classmethod
    def from_cv(
        cls,
        cv_keypoints: Sequence[CvKeypointLike],
        descriptors: np.ndarray,
        links: np.ndarray | None = None,
        config: CodecConfig = CodecConfig(),
    ) -> KeyframeFeatures:
        """Snap OpenCV ORB keypoints to the codec grid (does not reorder; call canonical())."""
        n = len(cv_keypoints)
        kp = np.zeros((n, 4), dtype=np.int32)
        if n:
            pts = np.array([k.pt for k in cv_keypoints], dtype=np.float64)
            lev = np.array([k.octave & 0xFF for k in cv_keypoints], dtype=np.int64)
            ang = np.array([k.angle for k in cv_keypoints], dtype=np.float64)
            s = config.level_scale(lev)
            kp[:, :2] = np.floor(pts / s[:, None] + 0.5)
            kp[:, 2] = lev
            kp[:, 3] = angle_to_bin(ang, config.angle_bins)
        if links is None:
            links = np.full(n, -1, dtype=np.int32)
        desc = np.zeros((0, 32), np.uint8) if descriptors is None else descriptors
        return cls(kp, desc, links)


def angle_to_bin(angle_deg: np.ndarray, bins: int = 32) -> np.ndarray:
    """Orientation bin of angles in degrees: ``floor(angle / 360 * bins) mod bins``."""
    a = np.asarray(angle_deg, dtype=np.float64)
    return (np.floor(a / 360.0 * bins).astype(np.int64) % bins).astype(np.int32)


@dataclass(frozen=True)
class NonKeyframeFeatures:
    """Tracked keypoints of a non-keyframe.

    survived: (P,) bool, one entry per active track of the previous frame.
    keypoints: (N, 3) float64 ``[u, v, l]``; the first ``survived.sum()`` rows are the
        survivors in order, the rest are new tracks. ``u, v`` are level-0 px on the
        ``1/subpixel`` grid (use :func:`quantise_uv`), ``l`` the pyramid level.
    """

    survived: np.ndarray
    keypoints: np.ndarray

    def __post_init__(self) -> None:
        sv = np.array(np.asarray(self.survived), dtype=bool).reshape(-1)
        sv.setflags(write=False)
        kp = _as_array(self.keypoints, np.float64, (3,), "keypoints")
        if kp.shape[0] < int(sv.sum()):
            raise CodecUsageError(
                f"{int(sv.sum())} tracks survived but only {kp.shape[0]} keypoints given"
            )
        object.__setattr__(self, "survived", sv)
        object.__setattr__(self, "keypoints", kp)

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])

    @property
    def n_new(self) -> int:
        return int(self.keypoints.shape[0] - self.survived.sum())

    def equals(self, other: NonKeyframeFeatures) -> bool:
        return np.array_equal(self.survived, other.survived) and np.array_equal(
            self.keypoints, other.keypoints
        )


def quantise_uv(uv: np.ndarray, config: CodecConfig = CodecConfig()) -> np.ndarray:
    """Snap level-0 pixel coordinates ``(N, 2)`` to the non-keyframe grid (round half up)."""
    return np.floor(np.asarray(uv, dtype=np.float64) * config.subpixel + 0.5) / config.subpixel


@dataclass(frozen=True)
class ImuChunk:
    """IMU samples in time order.

    timestamps_ns: (M,) int64 ns. gyro: (M, 3) float64 rad/s. accel: (M, 3) float64 m/s^2.
    Any float64 values round-trip bit-exactly; values on the sensor's lattice are cheap.
    """

    timestamps_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray

    def __post_init__(self) -> None:
        ts = np.array(np.asarray(self.timestamps_ns), dtype=np.int64).reshape(-1)
        ts.setflags(write=False)
        g = _as_array(self.gyro, np.float64, (3,), "gyro")
        a = _as_array(self.accel, np.float64, (3,), "accel")
        if not (ts.shape[0] == g.shape[0] == a.shape[0]):
            raise CodecUsageError("timestamps, gyro and accel must have the same length")
        object.__setattr__(self, "timestamps_ns", ts)
        object.__setattr__(self, "gyro", g)
        object.__setattr__(self, "accel", a)

    def __len__(self) -> int:
        return int(self.timestamps_ns.shape[0])

    def equals(self, other: ImuChunk) -> bool:
        return (
            np.array_equal(self.timestamps_ns, other.timestamps_ns)
            and self.gyro.tobytes() == other.gyro.tobytes()
            and self.accel.tobytes() == other.accel.tobytes()
        )

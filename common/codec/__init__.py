"""Lossless feature codec: keyframes (keypoints, word, XOR residual / inter), non-keyframes
(predicted keypoints, survival), IMU. See ``frames.py`` for the payload layout and state."""

from common.codec.errors import CodecError, CodecUsageError
from common.codec.frames import (
    FeatureCodecState,
    FeatureDecoder,
    FeatureEncoder,
    decode_standalone_keyframe,
    encode_standalone_keyframe,
    fill_carried,
)
from common.codec.imu import ImuCodecConfig, ImuDecoder, ImuEncoder, dequantise_imu
from common.codec.types import (
    CodecConfig,
    ImuChunk,
    KeyframeFeatures,
    NonKeyframeFeatures,
    angle_to_bin,
    quantise_uv,
)

__all__ = [
    "CodecConfig",
    "CodecError",
    "CodecUsageError",
    "FeatureCodecState",
    "FeatureDecoder",
    "FeatureEncoder",
    "ImuChunk",
    "ImuCodecConfig",
    "ImuDecoder",
    "ImuEncoder",
    "KeyframeFeatures",
    "NonKeyframeFeatures",
    "angle_to_bin",
    "decode_standalone_keyframe",
    "dequantise_imu",
    "encode_standalone_keyframe",
    "fill_carried",
    "quantise_uv",
]

"""Synthetic multi-robot EuRoC-layout dataset generator (scene, textures, flights, IMU, render).

Public entry: ``generate_dataset(out, SynthConfig(robots=3, seconds=60.0, seed=0))``.
"""

from common.data.synth.cameras import CAMERA_PRESETS, CameraPreset, camera_preset
from common.data.synth.generate import (
    EUROC_CAM0,
    GENERATOR_VERSION,
    DatasetSummary,
    RobotSummary,
    SynthConfig,
    SynthError,
    dataset_settings,
    generate_dataset,
)

__all__ = [
    "CAMERA_PRESETS",
    "EUROC_CAM0",
    "GENERATOR_VERSION",
    "CameraPreset",
    "DatasetSummary",
    "RobotSummary",
    "SynthConfig",
    "SynthError",
    "camera_preset",
    "dataset_settings",
    "generate_dataset",
]

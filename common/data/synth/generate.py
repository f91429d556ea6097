"""Multi-robot synthetic dataset generator: scene + textures + flights -> EuRoC-layout folders.

``generate_dataset(out, SynthConfig(robots=3, seconds=60, seed=0))`` writes::

    out/robot0/mav0/{cam0, imu0, state_groundtruth_estimate0, body.yaml}
    out/robot1/mav0/...
    out/dataset.json           seed, robots, seconds, generator version, per-robot facts
                               (and the camera preset of each robot when not all euroc)
    out/contact_sheet.png      sample frames of each robot
    out/trajectories_top.png   top view of the room, boxes and flights

Time: IMU and ground truth at 200 Hz on a grid starting at ``start_ns``; robot ``k`` starts
``k * robot_start_offset_s`` later (they fly at the same time, with different loop phases);
camera frames at 20 Hz are every 10th IMU sample. Everything is deterministic in ``seed``.
Each robot has its own camera (``SynthConfig.cameras``, presets of
:mod:`common.data.synth.cameras`; default all ``euroc``) stated in its ``cam0/sensor.yaml``.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from dataclasses import asdict, dataclass, field, is_dataclass
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np

from common.calibration import EUROC_IMU, CameraCalibration, ImuCalibration
from common.data.euroc import EurocGroundTruth
from common.data.euroc_write import EurocWriter
from common.data.synth.cameras import (
    CAMERA_PRESETS,
    EUROC_CAM0,
    CameraPreset,
    CameraPresetError,
    camera_preset,
)
from common.data.synth.flights import FlightConfig, make_flights, parse_flight
from common.data.synth.imu_sim import ImuNoiseConfig, simulate_imu
from common.data.synth.plots import contact_sheet, plot_top_view
from common.data.synth.recorded import RecordedFlight, recorded_flights
from common.data.synth.recorded_imu import RecordedImu, check_covers, read_recorded_imu
from common.data.synth.render import EffectsConfig, RenderConfig, Renderer
from common.data.synth.textures import TextureConfig, build_atlas
from common.data.synth.trajectory import (
    Motion,
    TrajectoryConfig,
    TrajectoryError,
    continuous_quaternions,
)
from common.data.synth.worlds import WORLDS, make_world
from common.errors import RecslamError
from common.geometry import R_to_quat_wxyz

logger = logging.getLogger(__name__)

GENERATOR_VERSION = "recslam-synth-1"

HARDER_KEYS = (
    "flight",
    "world",
    "trajectory_files",
    "effects",
    "flights",
    "imu_files",
    "time_offset_ms",
)
"""SynthConfig fields that dataset.json's ``config`` holds only when an issue-17 option is
used (:meth:`SynthConfig.harder`), so the default dataset's ``dataset.json`` stays byte for
byte what it was."""

__all__ = [
    "EUROC_CAM0",
    "GENERATOR_VERSION",
    "DatasetSummary",
    "RobotSummary",
    "SynthConfig",
    "SynthError",
    "camera_calibration",
    "generate_dataset",
    "imu_calibration",
    "robot_timestamps",
]


class SynthError(RecslamError):
    """Invalid generator settings or output folder."""


@dataclass(frozen=True)
class SynthConfig:
    """What to generate.

    ``robots``: number of sequences; ``seconds``: length of each [s]; ``seed``: everything
    random (textures, flights, noise) derives from it; ``camera_rate_hz`` (20) must divide
    ``imu_rate_hz`` (200); ``start_ns``: timestamp of robot 0's first sample [ns];
    ``robot_start_offset_s``: extra start delay of each further robot [s]; ``imu_noise`` /
    ``render`` / ``textures`` / ``trajectory``: sub-configs (set ``imu_noise.enabled=False``
    and ``render.noise_std=0`` for noise-free data); ``cameras``: one camera preset name per
    robot (:data:`~common.data.synth.cameras.CAMERA_PRESETS`), empty = all ``euroc``;
    ``contact_sheet``: write the PNG previews; ``progress``: tqdm bar on stderr.
    Harder worlds (issue 17): ``flight``: trajectory family and modifiers
    (:func:`~common.data.synth.flights.parse_flight`, default ``ring``); ``world``: scene
    (:data:`~common.data.synth.worlds.WORLDS`, default ``vicon``; a world brings its own
    texture resolution, used unless ``textures`` is not the default); ``trajectory_files``: one
    recorded ground truth per robot to fly instead of a family
    (:mod:`~common.data.synth.recorded`); ``effects``: exposure steps and motion blur;
    ``flights``: limits and style of the families (``trajectory`` is the ring's).
    Real sensors (issue 46): ``imu_files``: one recorded IMU per trajectory file, flown
    instead of the simulated IMU (:mod:`~common.data.synth.recorded_imu`);
    ``time_offset_ms``: the IMU clock runs this far ahead of the camera's
    (``t_imu = t_cam + offset``), an unsynchronised sensor.
    ``scene_seed``: the room's appearance (textures, posters, ``room-random``'s furniture)
    derives from it instead of ``seed`` (None: from ``seed``): datasets of one scene seed and
    different seeds are different flights through one room, e.g. two missions, one starting
    in the map the other left (``services.cloud.store.mission``).
    """

    robots: int = 3
    seconds: float = 60.0
    seed: int = 0
    camera_rate_hz: float = 20.0
    imu_rate_hz: float = 200.0
    start_ns: int = 1_600_000_000_000_000_000
    robot_start_offset_s: float = 1.0
    imu_noise: ImuNoiseConfig = field(default_factory=ImuNoiseConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    textures: TextureConfig = field(default_factory=TextureConfig)
    trajectory: TrajectoryConfig = field(default_factory=TrajectoryConfig)
    contact_sheet: bool = True
    progress: bool = True
    cameras: tuple[str, ...] = ()
    flight: str = "ring"
    world: str = "vicon"
    trajectory_files: tuple[str, ...] = ()
    effects: EffectsConfig = field(default_factory=EffectsConfig)
    flights: FlightConfig = field(default_factory=FlightConfig)
    scene_seed: int | None = None
    imu_files: tuple[str, ...] = ()
    time_offset_ms: float = 0.0

    @property
    def room_seed(self) -> int:
        """The seed of the room's appearance: ``scene_seed``, else ``seed``."""
        return self.seed if self.scene_seed is None else self.scene_seed

    def __post_init__(self) -> None:
        if self.robots < 1:
            raise SynthError(f"robots must be >= 1, got {self.robots}")
        if not self.seconds > 0:
            raise SynthError(f"seconds must be > 0, got {self.seconds}")
        ratio = self.imu_rate_hz / self.camera_rate_hz
        if abs(ratio - round(ratio)) > 1e-9 or ratio < 1:
            raise SynthError(
                f"imu_rate_hz {self.imu_rate_hz} must be a multiple of camera_rate_hz "
                f"{self.camera_rate_hz}"
            )
        if (1e9 / self.imu_rate_hz) % 1 != 0:
            raise SynthError(f"imu_rate_hz {self.imu_rate_hz} must give an integer ns period")
        object.__setattr__(self, "cameras", tuple(self.cameras))
        if self.cameras and len(self.cameras) != self.robots:
            raise SynthError(
                f"cameras: {len(self.cameras)} presets ({', '.join(self.cameras)}) "
                f"for {self.robots} robots: give one per robot"
            )
        for name in self.cameras:
            try:
                camera_preset(name)
            except CameraPresetError as e:
                raise SynthError(str(e)) from None
        try:
            object.__setattr__(self, "flight", parse_flight(self.flight).name)
        except TrajectoryError as e:
            raise SynthError(str(e)) from None
        if self.world not in WORLDS:
            raise SynthError(f"world {self.world!r}: unknown (known: {', '.join(WORLDS)})")
        object.__setattr__(self, "trajectory_files", tuple(str(f) for f in self.trajectory_files))
        if self.trajectory_files:
            if len(self.trajectory_files) != self.robots:
                raise SynthError(
                    f"{len(self.trajectory_files)} trajectory files for {self.robots} robots: "
                    "give one per robot"
                )
            if self.flight != "ring":
                raise SynthError(f"flight {self.flight!r} and trajectory files exclude each other")
        object.__setattr__(self, "imu_files", tuple(str(f) for f in self.imu_files))
        if self.imu_files and len(self.imu_files) != len(self.trajectory_files):
            raise SynthError(
                f"{len(self.imu_files)} IMU files for {len(self.trajectory_files)} trajectory "
                "files: a recorded IMU flies along the ground truth recorded with it, one each"
            )
        if abs(self.time_offset_ms) >= 1e3 / self.camera_rate_hz * 4:
            raise SynthError(
                f"time offset {self.time_offset_ms} ms: more than four camera frames; "
                "a camera-IMU offset is a few to a few tens of ms"
            )
        frame_ms = 1e3 / self.camera_rate_hz
        if not 0 <= self.effects.motion_blur_ms < frame_ms:
            raise SynthError(
                f"motion blur {self.effects.motion_blur_ms} ms: must be >= 0 and shorter than "
                f"a frame ({frame_ms:g} ms)"
            )

    def harder(self) -> dict[str, Any]:
        """The issue-17 options: flight, world, trajectory files, exposure steps, motion blur
        [ms] (what ``dataset.json`` records when any differs from the default)."""
        return {
            "flight": self.flight,
            "world": self.world,
            "trajectory_files": list(self.trajectory_files),
            "exposure_steps": self.effects.exposure_steps,
            "motion_blur_ms": float(self.effects.motion_blur_ms),
            "imu_files": list(self.imu_files),
            "time_offset_ms": float(self.time_offset_ms),
        }

    def camera(self, robot: int) -> CameraPreset:
        """Camera preset of robot ``robot``."""
        return camera_preset(self.cameras[robot]) if self.cameras else CAMERA_PRESETS["euroc"]


@dataclass(frozen=True)
class RobotSummary:
    """Facts about one generated sequence."""

    name: str
    path: str
    frames: int
    imu_samples: int
    first_timestamp_ns: int
    path_length_m: float
    max_speed_mps: float
    max_rate_radps: float


@dataclass(frozen=True)
class DatasetSummary:
    """What :func:`generate_dataset` wrote (``out`` folder, settings, per-robot facts, and the
    wall time [s] and rendering rate [frames/s])."""

    out: str
    robots: int
    seconds: float
    seed: int
    version: str
    sequences: tuple[RobotSummary, ...]
    wall_time_s: float
    render_fps: float

    def to_json(self) -> dict:
        return asdict(self)


DEFAULT_CONFIG = SynthConfig()
DEFAULT_HARDER = DEFAULT_CONFIG.harder()


def imu_calibration(config: SynthConfig) -> ImuCalibration:
    """EuRoC's ADIS16448 densities at the configured rate (IMU = body frame)."""
    return ImuCalibration(
        gyro_noise_density=EUROC_IMU.gyro_noise_density,
        gyro_random_walk=EUROC_IMU.gyro_random_walk,
        accel_noise_density=EUROC_IMU.accel_noise_density,
        accel_random_walk=EUROC_IMU.accel_random_walk,
        rate_hz=config.imu_rate_hz,
    )


def camera_calibration(config: SynthConfig, robot: int = 0) -> CameraCalibration:
    """Robot ``robot``'s camera (intrinsics, distortion, ``T_BS``; EuRoC cam0 by default) at
    the configured rate."""
    return config.camera(robot).calibration(config.camera_rate_hz)


def robot_timestamps(config: SynthConfig, robot: int) -> tuple[np.ndarray, np.ndarray, int]:
    """(IMU timestamps (M,) int64, camera frame indices into them (N,), t0_ns) of ``robot``."""
    period_ns = round(1e9 / config.imu_rate_hz)
    step = round(config.imu_rate_hz / config.camera_rate_hz)
    n = int(np.floor(config.seconds * config.imu_rate_hz + 1e-9)) + 1
    t0 = config.start_ns + round(robot * config.robot_start_offset_s * 1e9)
    ts = t0 + period_ns * np.arange(n, dtype=np.int64)
    return ts, np.arange(0, n, step), t0


class _Progress(Protocol):
    """What :func:`_write_robot` needs of its progress bar (a ``tqdm``)."""

    def update(self, n: int = 1) -> object: ...


def _write_robot(
    out: Path,
    k: int,
    config: SynthConfig,
    traj: Motion,
    renderer: Renderer,
    bar: _Progress,
    recorded: RecordedImu | None = None,
) -> tuple[RobotSummary, list[np.ndarray], dict[str, Any]]:
    """Simulate (or take the ``recorded`` IMU), render and write robot ``k``; returns its
    summary and sample frames."""
    name = f"robot{k}"
    ts, cam_idx, t0 = robot_timestamps(config, k)
    t = (ts - t0) * 1e-9
    imu_calib = imu_calibration(config)
    if recorded is None:
        imu = simulate_imu(
            traj, ts, t0, imu_calib, config.imu_noise, np.random.default_rng([config.seed, 202, k])
        )
        imu_ts = ts + round(config.time_offset_ms * 1e6)
        gyro, accel, bias_g, bias_a = imu.gyro, imu.accel, imu.bias_gyro, imu.bias_accel
    else:
        imu_ts, gyro, accel = recorded.window(config.seconds, t0, config.time_offset_ms)
        bias_g, bias_a = recorded.biases_at(t)
    st = traj.evaluate(t)
    gt = EurocGroundTruth(
        timestamps_ns=ts,
        p_world_body=st.p_world_body,
        q_world_body_wxyz=continuous_quaternions(R_to_quat_wxyz(st.R_world_body)),
        v_world_body=st.v_world_body,
        bias_gyro=bias_g,
        bias_accel=bias_a,
    )
    preset = config.camera(k)
    T_world_cam = st.T_world_cam(preset.T_body_cam)
    offsets = config.effects.subframe_offsets_s()
    sub: np.ndarray | None = None
    if len(offsets):
        t_sub = np.clip(t[cam_idx][:, None] + offsets[None], 0.0, t[-1])
        sub = traj.evaluate(t_sub.reshape(-1)).T_world_cam(preset.T_body_cam)
        sub = sub.reshape(len(cam_idx), len(offsets), 4, 4)
    steps_t, steps_gain = config.effects.exposure_schedule(
        config.seconds, np.random.default_rng([config.seed, 505, k])
    )
    gains = steps_gain[np.searchsorted(steps_t, t[cam_idx], side="right") - 1]
    samples: list[np.ndarray] = []
    sample_at = set(np.linspace(0, len(cam_idx) - 1, 4).round().astype(int).tolist())
    phase = float(np.random.default_rng([config.seed, 303, k]).uniform(0, 2 * np.pi))
    with EurocWriter(out / name, body_yaml_comment=f"recslam synthetic {name}") as w:
        w.add_camera("cam0", camera_calibration(config, k), comment=preset.comment)
        for j, i in enumerate(cam_idx):
            rng = np.random.default_rng([config.seed, 404, k, j])
            if sub is None and not config.effects.exposure_steps:
                img = renderer.render(T_world_cam[i], float(t[i]), rng, phase)
            else:
                poses = None if sub is None else sub[j]
                img = renderer.render(T_world_cam[i], float(t[i]), rng, phase, gains[j], poses)
            w.add_image("cam0", int(ts[i]), img)
            if j in sample_at:
                samples.append(img)
            bar.update(1)
        w.write_imu(imu_calib, imu_ts, gyro, accel)
        w.write_groundtruth(gt)
    steps = np.linalg.norm(np.diff(st.p_world_body, axis=0), axis=1)
    summary = RobotSummary(
        name=name,
        path=str(out / name),
        frames=len(cam_idx),
        imu_samples=len(imu_ts),
        first_timestamp_ns=int(ts[0]),
        path_length_m=float(steps.sum()),
        max_speed_mps=float(np.linalg.norm(st.v_world_body, axis=1).max()),
        max_rate_radps=float(np.linalg.norm(st.omega_body, axis=1).max()),
    )
    extra: dict[str, Any] = {}
    if recorded is not None:
        extra["imu"] = recorded.describe()
    if config.effects.exposure_steps:
        extra["exposure_steps"] = {"t_s": steps_t.tolist(), "gain": steps_gain.tolist()}
    return summary, samples, extra


def _describe(flight: Motion) -> dict[str, Any]:
    """What ``dataset.json`` records of a flight: a recorded one's description, else the
    fields of the flight's dataclass."""
    if isinstance(flight, RecordedFlight):
        return flight.describe()
    if not is_dataclass(flight) or isinstance(flight, type):
        raise SynthError(f"flight {flight!r} has no description")
    return asdict(flight)


def _clear_previous(out: Path) -> None:
    """Remove what an earlier run of this generator wrote into ``out`` (its ``dataset.json``
    and ``robotK`` folders whose ``body.yaml`` names this generator), so no stale frames stay."""
    (out / "dataset.json").unlink(missing_ok=True)
    for folder in sorted(out.glob("robot*")):
        body = folder / "mav0" / "body.yaml"
        if folder.name[5:].isdigit() and body.is_file() and "recslam synthetic" in body.read_text():
            logger.info("removing previous %s", folder)
            shutil.rmtree(folder)


def dataset_settings(folder: Path) -> dict[str, Any] | None:
    """The settings a synthetic dataset in ``folder`` was built with, from its
    ``dataset.json``: ``robots``, ``seconds`` (float), ``seed``, ``cameras`` (a tuple, empty
    for all-EuRoC) and the issue-17 options of :meth:`SynthConfig.harder` (``flight``,
    ``world``, ``trajectory_files`` as a tuple, ``exposure_steps``, ``motion_blur_ms``; their
    defaults when the file does not state them); None when ``folder`` holds none."""
    meta = Path(folder) / "dataset.json"
    if not meta.is_file():
        return None
    info = json.loads(meta.read_text())
    harder = DEFAULT_HARDER | info.get("harder", {})
    return (
        {
            "robots": info.get("robots"),
            "seconds": float(info.get("seconds", -1)),
            "seed": info.get("seed"),
            "cameras": tuple(info.get("config", {}).get("cameras", ())),
        }
        | harder
        | {
            "trajectory_files": tuple(harder["trajectory_files"]),
            "imu_files": tuple(harder["imu_files"]),
        }
    )


def generate_dataset(out: Path, config: SynthConfig = SynthConfig()) -> DatasetSummary:
    """Generate the whole dataset into ``out`` (created if needed) and return its summary."""
    from tqdm import tqdm

    start = time.perf_counter()
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise SynthError(f"{out}: exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    _clear_previous(out)
    world = make_world(config.world, config.room_seed)
    scene = world.scene
    # A world's own texture resolution unless the config asks for other textures.
    textures = world.textures if config.textures == TextureConfig() else config.textures
    atlas = build_atlas(scene, config.room_seed, textures)
    renderers: dict[str, Renderer] = {}
    for k in range(config.robots):
        preset = config.camera(k)
        if preset.name not in renderers:
            renderers[preset.name] = Renderer(scene, atlas, preset.model, config.render)
    trajectories: list[Motion]
    try:
        if config.trajectory_files:
            files = config.trajectory_files
            trajectories = [
                *recorded_flights(
                    scene,
                    world.region,
                    files,
                    config.seconds,
                    world.name,
                    recorded_imu=bool(config.imu_files),
                )
            ]
        else:
            spec = parse_flight(config.flight)
            trajectories = [
                *make_flights(
                    scene,
                    world.region,
                    spec,
                    config.robots,
                    config.seconds,
                    config.seed,
                    config.trajectory,
                    config.flights,
                )
            ]
        recorded_imus: list[RecordedImu | None] = [None] * config.robots
        for k, f in enumerate(config.imu_files):
            rec_imu = read_recorded_imu(f, config.trajectory_files[k])
            check_covers(rec_imu, config.seconds)
            recorded_imus[k] = rec_imu
    except TrajectoryError as e:
        raise SynthError(str(e)) from None
    frames_per_robot = len(robot_timestamps(config, 0)[1])
    summaries, samples, extras = [], [], []
    render_start = time.perf_counter()
    with tqdm(
        total=frames_per_robot * config.robots,
        desc="rendering",
        unit="frame",
        disable=not config.progress,
    ) as bar:
        for k, traj in enumerate(trajectories):
            renderer = renderers[config.camera(k).name]
            s, frames, extra = _write_robot(out, k, config, traj, renderer, bar, recorded_imus[k])
            summaries.append(s)
            samples.append(frames)
            extras.append(extra)
    render_time = time.perf_counter() - render_start
    if config.contact_sheet:
        cv2.imwrite(str(out / "contact_sheet.png"), contact_sheet(samples))
        plot_top_view(scene, trajectories, config.seconds, out / "trajectories_top.png")
    total_frames = sum(s.frames for s in summaries)
    summary = DatasetSummary(
        out=str(out),
        robots=config.robots,
        seconds=float(config.seconds),
        seed=config.seed,
        version=GENERATOR_VERSION,
        sequences=tuple(summaries),
        wall_time_s=time.perf_counter() - start,
        render_fps=total_frames / max(render_time, 1e-9),
    )
    meta: dict[str, Any] = {
        "generator": GENERATOR_VERSION,
        "robots": config.robots,
        "seconds": float(config.seconds),
        "seed": config.seed,
        "camera_rate_hz": config.camera_rate_hz,
        "imu_rate_hz": config.imu_rate_hz,
        "sequences": [
            asdict(s)
            | {"path": s.name}
            | ({"camera": config.cameras[k]} if config.cameras else {})
            | extras[k]
            for k, s in enumerate(summaries)
        ],
        # Without --cameras (or the harder worlds' options), dataset.json stays byte for byte
        # what it was before them.
        "config": {
            k: v
            for k, v in asdict(config).items()
            if k != "progress"
            and (k != "cameras" or config.cameras)
            and (k != "scene_seed" or config.scene_seed is not None)
            and (k not in HARDER_KEYS or config.harder() != DEFAULT_HARDER)
        },
        "room": {
            "lo": list(scene.room_lo),
            "hi": list(scene.room_hi),
            "boxes": [asdict(b) for b in scene.boxes],
        },
        "trajectories": [_describe(tr) for tr in trajectories],
    }
    if config.harder() != DEFAULT_HARDER:
        meta["harder"] = config.harder()
        meta["room"]["name"] = world.name
        meta["room"]["flight_region"] = [list(world.region[0]), list(world.region[1])]
        meta["room"]["textures"] = asdict(textures)
    (out / "dataset.json").write_text(json.dumps(meta, indent=2) + "\n")
    logger.info(
        "dataset %s: %d robots x %g s in %.1f s (%.1f frames/s)",
        out,
        config.robots,
        config.seconds,
        summary.wall_time_s,
        summary.render_fps,
    )
    return summary

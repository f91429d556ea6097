"""Calibration files as users have them: EuRoC / TUM-VI ``sensor.yaml`` and Kalibr's
``camchain.yaml`` + ``imu.yaml``.

Frames (see :mod:`common.calibration`): ``T_a_b`` maps points from frame ``b`` to frame ``a``.

- EuRoC (``mav0/cam0/sensor.yaml``, ``mav0/imu0/sensor.yaml``): ``T_BS`` is
  ``T_body_sensor``; TUM-VI's EuRoC-format folders state ``distortion_model: equidistant``.
- Kalibr (``camchain*.yaml``, ``imu*.yaml``): ``cam0.T_cam_imu`` maps IMU-frame points into
  the camera frame (OpenVINS's copies write its inverse as ``T_imu_cam``); the body frame is
  the IMU frame, so ``T_body_cam = inv(T_cam_imu)``, unless the IMU file states ``T_i_b``
  (body to IMU), then ``T_body_imu = inv(T_i_b)``. ``timeshift_cam_imu`` [s] is
  ``t_imu - t_cam``. Kalibr states no camera rate; the sequence measures it.

Every bad file raises :class:`CalibrationFileError` as ``<file>:<line>: <field> ...``: a
missing field, an unknown camera or distortion model, a wrong coefficient count, a transform
that is not rigid (orthonormal rotation with det +1, last row ``0 0 0 1``).
"""

from __future__ import annotations

import dataclasses
import enum
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from common.calibration import (
    CAMERA_MODELS,
    CalibrationError,
    CameraCalibration,
    ImuCalibration,
)
from common.errors import RecslamError
from common.geometry import orthonormalize_T, rigid_problem
from common.links.sensors import RIGID_TOLERANCE as WIRE_RIGID_TOLERANCE

logger = logging.getLogger(__name__)

RIGID_TOLERANCE = 1e-4
"""Largest entry of ``|RᵀR - I|`` and of the last row's difference from ``0 0 0 1``."""

EUROC_DISTORTION_MODELS = {
    "radial-tangential": "radtan",
    "radtan": "radtan",
    "equidistant": "equidistant",
}
"""``distortion_model`` of a EuRoC-format ``sensor.yaml`` -> :data:`CAMERA_MODELS` name."""

KALIBR_DISTORTION_MODELS = {"radtan": "radtan", "equidistant": "equidistant", "none": "radtan"}
"""``distortion_model`` of a Kalibr camchain -> :data:`CAMERA_MODELS` name (``none``: radtan
with zero coefficients, ``distortion_coeffs`` empty or absent)."""

KALIBR_CAMCHAIN_GLOBS = ("camchain*.yaml", "kalibr_imucam_chain.yaml")
KALIBR_IMU_GLOBS = ("imu.yaml", "imu-*.yaml", "kalibr_imu_chain.yaml")


class CalibrationFileError(CalibrationError):
    """A calibration file is missing, malformed, or describes no real sensor."""


class CalibrationFormat(enum.Enum):
    """Where a :class:`SensorCalibration` was read from."""

    EUROC = "euroc"
    """``mav0/camN/sensor.yaml`` and ``mav0/imu0/sensor.yaml`` (EuRoC, TUM-VI)."""
    KALIBR = "kalibr"
    """Kalibr's ``camchain.yaml`` and ``imu.yaml``."""


@dataclass(frozen=True, eq=False)
class SensorCalibration:
    """A robot's calibration: its cameras (``cameras[0]`` is the one the robot tracks with),
    its IMU, and where they came from.

    ``timeshift_cam_imu_s``: ``t_imu - t_cam`` [s] (Kalibr), added to the frame timestamps;
    ``camera_rate_stated``: False when the file gave no camera rate (the sequence then sets
    the measured one); ``image_topic`` / ``imu_topic``: Kalibr's ``rostopic`` entries.
    """

    cameras: tuple[CameraCalibration, ...]
    imu: ImuCalibration
    format: CalibrationFormat
    sources: tuple[Path, ...]
    timeshift_cam_imu_s: float = 0.0
    camera_rate_stated: bool = True
    image_topic: str | None = None
    imu_topic: str | None = None

    @property
    def cam0(self) -> CameraCalibration:
        return self.cameras[0]

    def describe(self) -> str:
        return f"{self.format.value} calibration ({', '.join(str(p) for p in self.sources)})"

    def with_camera_rate(self, rate_hz: float) -> SensorCalibration:
        """The same calibration with the measured camera rate if the file stated none."""
        if self.camera_rate_stated or not (math.isfinite(rate_hz) and rate_hz > 0):
            return self
        cams = tuple(dataclasses.replace(c, rate_hz=rate_hz) for c in self.cameras)
        return dataclasses.replace(self, cameras=cams, camera_rate_stated=True)


# ---------------------------------------------------------------------------- YAML files


def read_text(path: Path, error: type[RecslamError] = CalibrationFileError) -> str:
    """The UTF-8 text of ``path`` (BOM dropped); ``error`` names a missing or binary file."""
    if not path.is_file():
        raise error(f"{path}: missing file")
    try:
        return path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise error(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None


class _YamlLoader(yaml.SafeLoader):
    """SafeLoader that also reads OpenCV ``!!opencv-matrix`` nodes as plain mappings."""


_YamlLoader.add_constructor(
    "tag:yaml.org,2002:opencv-matrix",
    lambda loader, node: loader.construct_mapping(node, deep=True),
)


class YamlSection:
    """A mapping of a YAML file: values by key, the line of each key, typed accessors whose
    errors name ``<file>:<line>`` and the field (``cam0.intrinsics`` inside a section)."""

    def __init__(self, path: Path, data: dict, node: yaml.Node, prefix: str = "") -> None:
        self.path = path
        self.data = data
        self.prefix = prefix
        pairs = node.value if isinstance(node, yaml.MappingNode) else []
        self.lines = {k.value: k.start_mark.line + 1 for k, _ in pairs}
        self._nodes = {k.value: v for k, v in pairs}

    def name(self, key: str) -> str:
        return f"{self.prefix}{key}"

    def where(self, key: str) -> str:
        return f"{self.path}:{self.lines[key]}" if key in self.lines else str(self.path)

    def has(self, key: str) -> bool:
        return key in self.data

    def get(self, key: str) -> object:
        if key not in self.data:
            raise CalibrationFileError(f"{self.path}: missing field {self.name(key)!r}")
        return self.data[key]

    def section(self, key: str) -> YamlSection:
        value = self.get(key)
        if not isinstance(value, dict):
            raise CalibrationFileError(f"{self.where(key)}: {self.name(key)} must be a mapping")
        return YamlSection(self.path, value, self._nodes[key], f"{self.name(key)}.")

    def fail(self, key: str, what: str) -> CalibrationFileError:
        return CalibrationFileError(f"{self.where(key)}: {self.name(key)} {what}")

    def number(self, key: str, positive: bool = False) -> float:
        value = self.get(key)
        try:
            if isinstance(value, bool) or not isinstance(value, int | float | str):
                raise TypeError
            x = float(value)  # PyYAML reads "1e-3" (no dot) as a string
        except (TypeError, ValueError):
            raise self.fail(key, f"must be a number, got {value!r}") from None
        if not math.isfinite(x) or x < 0 or (positive and x == 0):
            sign = "positive" if positive else "non-negative"
            raise self.fail(key, f"must be a finite {sign} number, got {x}")
        return x

    def numbers(self, key: str, n: int | None = None, value: object = None) -> list[float]:
        """A list of ``n`` finite numbers (any length if None); an OpenCV matrix's ``data``."""
        value = self.get(key) if value is None else value
        if isinstance(value, dict) and "data" in value:
            value = value["data"]
        count = "" if n is None else f"{n} "
        try:
            if not isinstance(value, list) or (n is not None and len(value) != n):
                raise TypeError
            xs = [float(v) for v in value if not isinstance(v, bool)]
            if len(xs) != len(value) or not all(math.isfinite(x) for x in xs):
                raise TypeError
        except (TypeError, ValueError):
            raise self.fail(
                key, f"must be a list of {count}finite numbers, got {value!r}"
            ) from None
        return xs

    def transform(self, key: str) -> np.ndarray:
        """A rigid (4, 4) transform: EuRoC's ``{rows: 4, cols: 4, data: [16]}`` or Kalibr's
        four rows of four."""
        value = self.get(key)
        if isinstance(value, dict):
            if value.get("rows") != 4 or value.get("cols") != 4:
                raise self.fail(key, "must be a mapping with rows: 4, cols: 4")
            T = np.array(self.numbers(key, 16, value.get("data"))).reshape(4, 4)
        elif (
            isinstance(value, list) and len(value) == 4 and all(isinstance(r, list) for r in value)
        ):
            T = np.array([self.numbers(key, 4, row) for row in value])
        else:
            raise self.fail(key, f"must be 4 rows of 4 numbers, got {value!r}")
        return check_rigid(T, f"{self.where(key)}: {self.name(key)}")

    def choice(self, key: str, allowed: dict[str, str], default: str | None = None) -> str:
        """The canonical name of a string field among ``allowed`` (``default`` if absent)."""
        if default is not None and key not in self.data:
            return default
        value = self.get(key)
        if value not in allowed:
            raise self.fail(key, f"is {value!r}, supported: {', '.join(allowed)}")
        return allowed[str(value)]

    def text(self, key: str) -> str | None:
        value = self.data.get(key)
        return None if value is None else str(value)


def load_yaml(path: Path) -> YamlSection:
    """Parse a YAML file (OpenCV's ``%YAML:1.0`` directive tolerated) into its top mapping."""
    lines = read_text(path).splitlines()
    if lines and lines[0].startswith("%YAML"):
        lines[0] = ""  # OpenCV's "%YAML:1.0" directive; keep line numbers stable
    loader = _YamlLoader("\n".join(lines))
    try:
        node = loader.get_single_node()
        data = loader.construct_document(node) if node is not None else None
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark is not None else str(path)
        problem = getattr(e, "problem", None) or str(e)
        raise CalibrationFileError(f"{where}: invalid YAML: {problem}") from None
    finally:
        loader.dispose()
    if not isinstance(data, dict):
        raise CalibrationFileError(f"{path}: expected a YAML mapping at top level")
    return YamlSection(path, data, node)


def check_rigid(T: np.ndarray, what: str) -> np.ndarray:
    """``T`` (4, 4) if it is rigid within :data:`RIGID_TOLERANCE`, else CalibrationFileError
    naming ``what``. A file that prints few digits gives a rotation off SO(3) by more than
    the robot->edge link accepts (``common.links.sensors``): such a rotation is snapped onto
    SO(3); one as exact as the link wants is kept as the file states it."""
    why = rigid_problem(T, RIGID_TOLERANCE)
    if why:
        raise CalibrationFileError(f"{what} is not a rigid transform: {why}: {T.tolist()}")
    if rigid_problem(T, WIRE_RIGID_TOLERANCE):
        T = orthonormalize_T(T)
        T[3] = (0.0, 0.0, 0.0, 1.0)
    return T


def _camera(
    y: YamlSection,
    model: str,
    coeffs_key: str,
    T_body_cam: np.ndarray,
    rate_hz: float,
    undistorted: bool = False,
) -> CameraCalibration:
    """CameraCalibration of a pinhole section (intrinsics [fu, fv, pu, pv], resolution);
    ``undistorted``: zero coefficients, none may be stated."""
    y.choice("camera_model", {"pinhole": "pinhole"}, default="pinhole")
    resolution = y.numbers("resolution", 2)
    if not all(v == int(v) and v >= 1 for v in resolution):
        raise y.fail(
            "resolution", f"must be two positive integers [width, height], got {resolution}"
        )
    fx, fy, cx, cy = y.numbers("intrinsics", 4)
    if fx <= 0 or fy <= 0:
        raise y.fail("intrinsics", f"focal lengths must be positive, got {fx}, {fy}")
    names = CAMERA_MODELS[model]
    if undistorted:
        if y.has(coeffs_key) and any(y.numbers(coeffs_key)):
            raise y.fail(coeffs_key, "must be empty with distortion_model: none")
        coeffs = [0.0] * len(names)
    else:
        coeffs = y.numbers(coeffs_key)
    if len(coeffs) != len(names):
        raise y.fail(
            coeffs_key,
            f"has {len(coeffs)} coefficients; {model} takes {len(names)} ({', '.join(names)})",
        )
    try:
        return CameraCalibration(
            width=int(resolution[0]),
            height=int(resolution[1]),
            fx=fx,
            fy=fy,
            cx=cx,
            cy=cy,
            distortion=tuple(coeffs),
            T_body_cam=T_body_cam,
            rate_hz=rate_hz,
            model=model,
        )
    except CalibrationError as e:  # checked above; kept so a new rule still names the file
        raise CalibrationFileError(f"{y.path}: {y.prefix.rstrip('.') or 'camera'}: {e}") from None


# ---------------------------------------------------------------------------- EuRoC


def read_camera_yaml(path: Path | str) -> CameraCalibration:
    """EuRoC / TUM-VI ``camN/sensor.yaml`` -> :class:`CameraCalibration` (pinhole, radtan or
    equidistant)."""
    y = load_yaml(Path(path))
    y.choice("sensor_type", {"camera": "camera"}, default="camera")
    model = y.choice("distortion_model", EUROC_DISTORTION_MODELS)
    return _camera(
        y, model, "distortion_coefficients", y.transform("T_BS"), y.number("rate_hz", True)
    )


def read_imu_yaml(path: Path | str) -> ImuCalibration:
    """EuRoC ``imu0/sensor.yaml`` -> :class:`ImuCalibration` (continuous-time densities)."""
    y = load_yaml(Path(path))
    y.choice("sensor_type", {"imu": "imu"}, default="imu")
    return ImuCalibration(
        gyro_noise_density=y.number("gyroscope_noise_density"),
        gyro_random_walk=y.number("gyroscope_random_walk"),
        accel_noise_density=y.number("accelerometer_noise_density"),
        accel_random_walk=y.number("accelerometer_random_walk"),
        rate_hz=y.number("rate_hz", positive=True),
        T_body_imu=y.transform("T_BS"),
    )


def read_euroc(mav0: Path) -> SensorCalibration:
    """``mav0/cam0`` (and ``cam1`` if its ``sensor.yaml`` exists) and ``mav0/imu0``."""
    cams = [mav0 / "cam0" / "sensor.yaml"]
    if (mav0 / "cam1" / "sensor.yaml").is_file():
        cams.append(mav0 / "cam1" / "sensor.yaml")
    imu = mav0 / "imu0" / "sensor.yaml"
    return SensorCalibration(
        cameras=tuple(read_camera_yaml(p) for p in cams),
        imu=read_imu_yaml(imu),
        format=CalibrationFormat.EUROC,
        sources=(*cams, imu),
    )


# ---------------------------------------------------------------------------- Kalibr


def read_kalibr(camchain: Path | str, imu: Path | str) -> SensorCalibration:
    """Kalibr's ``camchain.yaml`` (``cam0`` is used) and ``imu.yaml`` (flat, or under
    ``imu0`` as Kalibr's results and OpenVINS write it)."""
    camchain, imu = Path(camchain), Path(imu)
    iy = load_yaml(imu)
    if isinstance(iy.data.get("imu0"), dict):
        iy = iy.section("imu0")
    T_body_imu = np.eye(4)
    if iy.has("T_i_b"):
        T_body_imu = np.linalg.inv(iy.transform("T_i_b"))
    imu_cal = ImuCalibration(
        gyro_noise_density=iy.number("gyroscope_noise_density"),
        gyro_random_walk=iy.number("gyroscope_random_walk"),
        accel_noise_density=iy.number("accelerometer_noise_density"),
        accel_random_walk=iy.number("accelerometer_random_walk"),
        rate_hz=iy.number("update_rate", positive=True),
        T_body_imu=T_body_imu,
    )
    top = load_yaml(camchain)
    if not top.has("cam0") and (top.has("intrinsics") or top.has("T_BS")):
        raise CalibrationFileError(
            f"{camchain}: no 'cam0' section: not a Kalibr camchain (a EuRoC sensor.yaml?)"
        )
    y = top.section("cam0")
    extra = sorted(k for k in top.data if k != "cam0")
    if extra:
        logger.info("%s: only cam0 is used (also present: %s)", camchain, ", ".join(extra))
    if y.has("T_cam_imu") and y.has("T_imu_cam"):
        raise y.fail("T_imu_cam", "given together with T_cam_imu: keep one")
    if y.has("T_imu_cam"):  # OpenVINS's kalibr_imucam_chain.yaml
        T_imu_cam = y.transform("T_imu_cam")
    elif y.has("T_cam_imu"):
        T_imu_cam = np.linalg.inv(y.transform("T_cam_imu"))
    else:
        raise CalibrationFileError(
            f"{camchain}: missing field 'cam0.T_cam_imu' (a camera-only calibration: run "
            "Kalibr's camera-IMU calibration for the IMU extrinsic)"
        )
    model = y.choice("distortion_model", KALIBR_DISTORTION_MODELS)
    stated = y.has("rate_hz")
    camera = _camera(
        y,
        model,
        "distortion_coeffs",
        T_body_imu @ T_imu_cam,
        y.number("rate_hz", positive=True) if stated else 20.0,
        undistorted=y.data.get("distortion_model") == "none",
    )
    shift = 0.0
    if y.has("timeshift_cam_imu"):
        value = y.get("timeshift_cam_imu")
        try:
            shift = float(value)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            raise y.fail("timeshift_cam_imu", f"must be a number [s], got {value!r}") from None
        if not math.isfinite(shift) or abs(shift) > 1.0:
            raise y.fail("timeshift_cam_imu", f"must be a finite shift under 1 s, got {shift}")
    return SensorCalibration(
        cameras=(camera,),
        imu=imu_cal,
        format=CalibrationFormat.KALIBR,
        sources=(camchain, imu),
        timeshift_cam_imu_s=shift,
        camera_rate_stated=stated,
        image_topic=y.text("rostopic"),
        imu_topic=iy.text("rostopic"),
    )


def _find_one(folder: Path, globs: tuple[str, ...], what: str) -> Path | None:
    found = sorted({p for g in globs for p in folder.glob(g) if p.is_file()})
    if len(found) > 1:
        imucam = [p for p in found if "imucam" in p.name]
        if len(imucam) == 1:
            return imucam[0]
        names = ", ".join(p.name for p in found)
        raise CalibrationFileError(
            f"{folder}: several {what} files ({names}): choose one with --calibration FILE"
        )
    return found[0] if found else None


def kalibr_imu_beside(camchain: Path) -> Path:
    """The Kalibr IMU file next to ``camchain`` (``imu.yaml``, ``imu-*.yaml``, ...)."""
    imu = _find_one(camchain.parent, KALIBR_IMU_GLOBS, "Kalibr IMU")
    if imu is None:
        globs = ", ".join(KALIBR_IMU_GLOBS)
        raise CalibrationFileError(
            f"{camchain}: no IMU calibration beside it (looked for {globs} in {camchain.parent})"
        )
    return imu


# ---------------------------------------------------------------------------- choosing


def _mav0_candidates(folder: Path) -> list[Path]:
    return [folder / "mav0", folder] if folder.name != "mav0" else [folder]


def find_calibration(folder: Path | str) -> SensorCalibration | None:
    """The calibration a sequence folder holds: EuRoC ``mav0/cam0/sensor.yaml`` first, else a
    Kalibr ``camchain*.yaml`` (with its ``imu*.yaml``) in the folder or its ``mav0``; None if
    there is neither."""
    folder = Path(folder)
    for mav0 in _mav0_candidates(folder):
        if (mav0 / "cam0" / "sensor.yaml").is_file():
            return read_euroc(mav0)
    for place in [folder, *_mav0_candidates(folder)]:
        camchain = _find_one(place, KALIBR_CAMCHAIN_GLOBS, "Kalibr camchain")
        if camchain is not None:
            return read_kalibr(camchain, kalibr_imu_beside(camchain))
    return None


def load_calibration(path: Path | str) -> SensorCalibration:
    """The calibration named by ``--calibration``: a folder (as :func:`find_calibration`), a
    Kalibr camchain (its IMU file beside it) or a EuRoC ``camN/sensor.yaml`` (IMU from
    ``../imu0/sensor.yaml``)."""
    path = Path(path)
    if path.is_dir():
        found = find_calibration(path)
        if found is None:
            raise CalibrationFileError(
                f"{path}: no calibration here (neither mav0/cam0/sensor.yaml nor a Kalibr "
                f"{' / '.join(KALIBR_CAMCHAIN_GLOBS)})"
            )
        return found
    y = load_yaml(path)
    if y.has("cam0"):
        return read_kalibr(path, kalibr_imu_beside(path))
    if y.has("T_BS") and y.has("intrinsics"):
        imu = path.parent.parent / "imu0" / "sensor.yaml"
        if not imu.is_file():
            raise CalibrationFileError(
                f"{path}: a EuRoC camera sensor.yaml needs its IMU's at {imu} (missing file)"
            )
        return SensorCalibration(
            cameras=(read_camera_yaml(path),),
            imu=read_imu_yaml(imu),
            format=CalibrationFormat.EUROC,
            sources=(path, imu),
        )
    raise CalibrationFileError(
        f"{path}: neither a Kalibr camchain (no 'cam0' section) nor a EuRoC camera sensor.yaml "
        "(no 'T_BS' and 'intrinsics')"
    )

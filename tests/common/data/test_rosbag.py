"""ROS bags as sequences: a ROS 1 .bag and a ROS 2 bag written with rosbags from the EuRoC
excerpt yield what the folder yields, and the robot codes byte-identical frames from them."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from common.data.euroc import EurocSequence
from common.data.rosbag import BagError, BagSequence, bag_summary, image_to_gray
from common.data.sources import SourceError, open_source
from common.errors import RecslamError
from common.links.robot_edge import RobotFrame, RobotSequenceEnd
from common.protocol import SessionConfig
from common.protocol.messages import encode_payload
from common.transport import Delivery, Server, TransportConfig, run
from common.vocabulary import Vocabulary
from recslam.cli import main as recslam_main
from services.robot.app import RobotApp
from services.robot.config import FrontEndConfig
from services.robot.server import RobotService
from services.robot.service_config import Rate, RobotServiceConfig

FRAMES = 8
IMAGE_TOPIC, IMU_TOPIC = "/cam0/image_raw", "/imu0"


def write_bag(
    path: Path, seq: EurocSequence, ros2: bool, encoding: str = "mono8", compressed: bool = False
) -> Path:
    """The first FRAMES frames of ``seq`` and its IMU up to 0.5 s after them, as a bag."""
    store = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    T = store.types
    image_type = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"

    def header(t: int, frame_id: str) -> Any:
        stamp = T["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9)
        extra = {} if ros2 else {"seq": 0}
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id, **extra)

    def vec(v: np.ndarray) -> Any:
        return T["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def image_msg(t: int, gray: np.ndarray) -> Any:
        if compressed:
            ok, png = cv2.imencode(".png", gray)
            assert ok
            return T[image_type](header=header(t, "cam0"), format="png", data=png.ravel())
        pixels = {"mono8": gray, "bgr8": cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)}[encoding]
        h, w = gray.shape
        return T[image_type](
            header=header(t, "cam0"),
            height=h,
            width=w,
            encoding=encoding,
            is_bigendian=0,
            step=pixels.strides[0],
            data=np.ascontiguousarray(pixels).ravel(),
        )

    def imu_msg(t: int, w: np.ndarray, a: np.ndarray) -> Any:
        return T["sensor_msgs/msg/Imu"](
            header=header(t, "imu0"),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=np.zeros(9),
            angular_velocity=vec(w),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=vec(a),
            linear_acceleration_covariance=np.zeros(9),
        )

    t_end = int(seq.frame_timestamps_ns[FRAMES - 1]) + 500_000_000
    messages: list[tuple[int, int, str, Any]] = []
    for k, t in enumerate(seq.frame_timestamps_ns[:FRAMES]):
        messages.append((int(t), 0, image_type, image_msg(int(t), seq.load_image(k))))
    for t, w, a in zip(seq.imu_timestamps_ns, seq.gyro, seq.accel, strict=True):
        if t <= t_end:
            messages.append((int(t), 1, "sensor_msgs/msg/Imu", imu_msg(int(t), w, a)))
    messages.sort(key=lambda m: (m[0], m[1]))
    writer = Writer2(path, version=9) if ros2 else Writer1(path)
    with writer:
        conns = [
            writer.add_connection(IMAGE_TOPIC, image_type, typestore=store),
            writer.add_connection(IMU_TOPIC, "sensor_msgs/msg/Imu", typestore=store),
        ]
        for t, c, msgtype, msg in messages:
            data = store.serialize_cdr(msg, msgtype) if ros2 else store.serialize_ros1(msg, msgtype)
            writer.write(conns[c], t, data)
    return path


@pytest.fixture(scope="module")
def folder(euroc_micro: Path) -> EurocSequence:
    return EurocSequence(euroc_micro)


@pytest.fixture(scope="module")
def bags(folder: EurocSequence, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp("bags")
    return {
        "ros1": write_bag(out / "micro.bag", folder, ros2=False),
        "ros2": write_bag(out / "micro_ros2", folder, ros2=True),
        "ros2_bgr8": write_bag(out / "micro_bgr8", folder, ros2=True, encoding="bgr8"),
        "ros1_png": write_bag(out / "micro_png.bag", folder, ros2=False, compressed=True),
    }


def open_bag_source(bag: Path, euroc_micro: Path) -> BagSequence:
    calib = euroc_micro / "mav0" / "cam0" / "sensor.yaml"
    source = open_source(bag=bag, calibration=calib, image_topic=IMAGE_TOPIC, imu_topic=IMU_TOPIC)
    assert isinstance(source, BagSequence)
    return source


@pytest.mark.parametrize("kind", ["ros1", "ros2", "ros2_bgr8", "ros1_png"])
def test_bag_yields_what_the_folder_yields(
    kind: str, bags: dict[str, Path], folder: EurocSequence, euroc_micro: Path
) -> None:
    bag = open_bag_source(bags[kind], euroc_micro)
    assert len(bag) == FRAMES
    np.testing.assert_array_equal(bag.frame_timestamps_ns, folder.frame_timestamps_ns[:FRAMES])
    np.testing.assert_array_equal(bag.cam0.T_body_cam, folder.cam0.T_body_cam)
    for a, b in zip(bag.frames(), folder.frames(0, FRAMES), strict=True):
        assert (a.index, a.timestamp_ns) == (b.index, b.timestamp_ns)
        assert a.image is not None and b.image is not None
        assert a.image.dtype == np.uint8 and a.image.shape == b.image.shape
        np.testing.assert_array_equal(a.image, b.image)
        np.testing.assert_array_equal(a.imu.timestamps_ns, b.imu.timestamps_ns)
        np.testing.assert_array_equal(a.imu.gyro, b.imu.gyro)
        np.testing.assert_array_equal(a.imu.accel, b.imu.accel)
    late = list(bag.frames(5, 7))  # a later start reads the same frames
    np.testing.assert_array_equal(late[0].image, folder.load_image(5))
    assert [f.index for f in late] == [5, 6]


def _coded(source: Any, camera: Any, imu: Any) -> list[bytes]:
    app = RobotApp(FrontEndConfig(), camera, imu, Vocabulary.load())
    return [
        encode_payload(app.process(f.timestamp_ns, f.image, f.imu))
        for f in source.frames(0, FRAMES)
    ]


@pytest.mark.parametrize("kind", ["ros1", "ros2"])
def test_robot_codes_identical_frames_from_bag_and_folder(
    kind: str, bags: dict[str, Path], folder: EurocSequence, euroc_micro: Path
) -> None:
    bag = open_bag_source(bags[kind], euroc_micro)
    from_bag = _coded(bag, bag.cam0, bag.imu)
    from_folder = _coded(folder, folder.cam0, folder.imu)
    assert len(from_bag) == FRAMES and all(from_bag)
    assert from_bag == from_folder


def test_kalibr_calibration_names_the_topics(
    bags: dict[str, Path], folder: EurocSequence, euroc_micro: Path, tmp_path: Path
) -> None:
    """Kalibr's ``rostopic`` entries are the default topics; its body frame is the IMU's."""
    T_cam_body = np.linalg.inv(folder.cam0.T_body_cam)
    rows = "".join(f"  - {row}\n" for row in T_cam_body.tolist())
    (tmp_path / "camchain-imucam-run.yaml").write_text(
        "cam0:\n  camera_model: pinhole\n  distortion_model: radtan\n"
        f"  distortion_coeffs: {list(folder.cam0.distortion)}\n"
        f"  intrinsics: {[folder.cam0.fx, folder.cam0.fy, folder.cam0.cx, folder.cam0.cy]}\n"
        f"  resolution: [752, 480]\n  rostopic: {IMAGE_TOPIC}\n  T_cam_imu:\n{rows}"
    )
    (tmp_path / "imu-run.yaml").write_text(
        f"accelerometer_noise_density: 2.0e-3\naccelerometer_random_walk: 3.0e-3\n"
        f"gyroscope_noise_density: 1.6968e-04\ngyroscope_random_walk: 1.9393e-05\n"
        f"rostopic: {IMU_TOPIC}\nupdate_rate: 200.0\n"
    )
    bag = open_source(bag=bags["ros2"], calibration=tmp_path)
    assert isinstance(bag, BagSequence) and (bag.image_topic, bag.imu_topic) == (
        IMAGE_TOPIC,
        IMU_TOPIC,
    )
    assert bag.cam0.rate_hz == pytest.approx(20.0)  # measured: Kalibr states none
    np.testing.assert_allclose(bag.cam0.T_body_cam, folder.cam0.T_body_cam, atol=1e-12)
    assert bag.summary()["frames"] == FRAMES


def test_bag_errors_name_the_topic(bags: dict[str, Path], euroc_micro: Path, tmp_path) -> None:
    calib = euroc_micro / "mav0" / "cam0" / "sensor.yaml"
    bag = bags["ros1"]
    with pytest.raises(BagError, match=r"no topic '/cam1/image_raw' \(topics: /cam0/image_raw"):
        open_source(bag=bag, calibration=calib, image_topic="/cam1/image_raw", imu_topic=IMU_TOPIC)
    with pytest.raises(BagError, match="topic '/imu0' holds sensor_msgs/msg/Imu, expected"):
        open_source(bag=bag, calibration=calib, image_topic=IMU_TOPIC, imu_topic=IMU_TOPIC)
    with pytest.raises(BagError, match="--imu-topic is required"):
        open_source(bag=bag, calibration=calib, image_topic=IMAGE_TOPIC)
    with pytest.raises(SourceError, match="a bag holds no calibration"):
        open_source(bag=bag, image_topic=IMAGE_TOPIC, imu_topic=IMU_TOPIC)
    (tmp_path / "x.bag").write_bytes(b"not a bag")
    with pytest.raises(BagError, match="unreadable bag"):
        open_source(bag=tmp_path / "x.bag", calibration=calib, image_topic="a", imu_topic="b")
    # A calibration whose resolution is not the images' stops at the first frame.
    wrong = tmp_path / "cam0" / "sensor.yaml"
    wrong.parent.mkdir()
    wrong.write_text(calib.read_text().replace("[752, 480]", "[640, 480]"))
    (tmp_path / "imu0").mkdir()
    (tmp_path / "imu0" / "sensor.yaml").write_text(
        (euroc_micro / "mav0" / "imu0" / "sensor.yaml").read_text()
    )
    with pytest.raises(RecslamError, match=r"image is 752x480, sensor.yaml says 640x480"):
        open_source(bag=bag, calibration=wrong, image_topic=IMAGE_TOPIC, imu_topic=IMU_TOPIC)


def test_dataset_info_on_a_bag(bags: dict[str, Path], capsys: pytest.CaptureFixture) -> None:
    s = bag_summary(bags["ros2"])
    topics = {t["topic"]: t for t in s["topics"]}
    assert topics[IMAGE_TOPIC]["messages"] == FRAMES
    assert topics[IMAGE_TOPIC]["type"] == "sensor_msgs/msg/Image"
    assert topics[IMAGE_TOPIC]["rate_hz"] == pytest.approx(20.0, rel=1e-3)
    assert topics[IMU_TOPIC]["rate_hz"] == pytest.approx(200.0, rel=1e-2)
    assert s["format"] == "ROS 2 bag"
    assert recslam_main(["dataset", "info", str(bags["ros1"])]) == 0
    out = capsys.readouterr().out
    assert "ROS 1 bag" in out and IMAGE_TOPIC in out and "sensor_msgs/msg/Imu" in out
    assert f"{FRAMES:>9}" in out
    assert recslam_main(["dataset", "info", "--json", str(bags["ros2"])]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["topics"] == s["topics"]


def test_robot_service_plays_a_bag_as_it_plays_the_folder(
    bags: dict[str, Path], euroc_micro: Path
) -> None:
    """The whole service (worker thread, ROS 2's SQLite reader) over a bag and over the folder:
    the same RobotFrame bytes reach the edge."""
    secret = b"robot-bag-test-secret"
    fast = TransportConfig(reconnect_initial_delay=0.02, reconnect_max_delay=0.3)

    async def play(**source: Any) -> list[bytes]:
        got: list[bytes] = []
        ended = asyncio.Event()

        async def on_message(d: Delivery) -> None:
            if isinstance(d.message, RobotFrame):
                got.append(encode_payload(d.message))
            elif isinstance(d.message, RobotSequenceEnd):
                ended.set()

        server = Server(SessionConfig("edge", "edge-test", secret), on_message, transport=fast)
        _, port = await server.start()
        try:
            config = RobotServiceConfig(
                edge_host="127.0.0.1",
                edge_port=port,
                agent_id="robot-1",
                secret=secret,
                rate=Rate.MAX,
                max_frames=FRAMES - 2,
                flush_timeout_s=30.0,
                **source,
            )
            result = await RobotService(config, fast).run()
            await asyncio.wait_for(ended.wait(), 5)
        finally:
            await server.close()
        assert result.flushed and result.frames == FRAMES - 2
        return got

    from_folder = run(play(dataset=euroc_micro))
    from_bag = run(
        play(
            dataset=None,
            bag=bags["ros2"],
            calibration=euroc_micro / "mav0" / "cam0" / "sensor.yaml",
            image_topic=IMAGE_TOPIC,
            imu_topic=IMU_TOPIC,
        )
    )
    assert len(from_bag) == FRAMES - 2 and from_bag == from_folder


def test_image_encodings_give_the_folder_readers_gray(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    img16 = rng.integers(0, 65536, (6, 5), dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "x.png"), img16)
    from_png = cv2.imread(str(tmp_path / "x.png"), cv2.IMREAD_GRAYSCALE)
    gray = (img16 >> 8).astype(np.uint8)

    def msg(encoding: str, pixels: np.ndarray, big: int = 0, pad: int = 0) -> SimpleNamespace:
        rows = pixels.reshape(pixels.shape[0], -1).view(np.uint8)
        rows = np.pad(rows, ((0, 0), (0, pad)))  # row padding: step > width * bytes
        fields = dict(encoding=encoding, height=6, width=5, is_bigendian=big)
        return SimpleNamespace(step=rows.shape[1], data=rows.ravel(), **fields)

    image = "sensor_msgs/msg/Image"
    np.testing.assert_array_equal(image_to_gray(msg("mono16", img16), image, "m"), from_png)
    big = msg("16UC1", img16.astype(">u2"), big=1, pad=3)
    np.testing.assert_array_equal(image_to_gray(big, image, "m"), from_png)
    rgb = cv2.cvtColor(gray, cv2.COLOR_GRAY2RGB)
    np.testing.assert_array_equal(image_to_gray(msg("rgb8", rgb, pad=1), image, "m"), gray)
    with pytest.raises(BagError, match="m: image encoding 'yuv422' not supported"):
        image_to_gray(msg("yuv422", gray), image, "m")
    with pytest.raises(BagError, match="has 30 bytes"):
        image_to_gray(msg("bgr8", gray), image, "m")

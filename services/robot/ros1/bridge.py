"""The ROS 1 bridge process (Debian's ``/usr/bin/python3``, where ``rospy`` is): topics <-> socket.

Run as ``python3 -m services.robot.ros1.bridge --mode robot|player --socket PATH ...`` by
:mod:`services.robot.ros1.source` (mode ``robot``) or a test player (mode ``player``); it
connects to the Unix socket at ``PATH`` and speaks :mod:`services.robot.ros1.wire`.

- ``robot``: subscribes to ``--image-topic`` (``sensor_msgs/Image``) and ``--imu-topic``
  (``sensor_msgs/Imu``) and forwards every message with its header stamp; for every pose the
  robot sends back it publishes ``nav_msgs/Odometry`` on ``--odom-topic`` (``header.frame_id``
  = ``--map-frame``, ``child_frame_id`` = ``--base-frame``, stamped with the camera time of
  the frame) and the TF ``map -> base_link`` alike; once the cloud has placed the robot's map
  in its global map, the (latched) TF ``--global-frame -> --map-frame`` of that placement.
- ``player``: publishes the IMU and images the socket brings on those topics (with their
  stamps) and reports the stamp of every Odometry message it sees on ``--odom-topic``.

Only this module imports ``rospy``; it uses the standard library and ROS's own packages
only (no numpy, nothing of the project but the wire format). It exits when the socket closes.
"""

from __future__ import annotations

import argparse
import logging
import socket
import sys
import threading
from collections.abc import Iterator

import rospy
import tf2_ros
from geometry_msgs.msg import TransformStamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Image, Imu

from services.robot.ros1 import wire

logger = logging.getLogger("recslam.ros1.bridge")


class Link:
    """The socket to the robot (or the player's driver): one writer lock, one reader."""

    def __init__(self, path: str) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.connect(path)
        self.lock = threading.Lock()
        self.reader = wire.FrameReader()

    def send(self, data: bytes) -> None:
        with self.lock:
            self.sock.sendall(data)

    def frames(self) -> Iterator[tuple[int, bytes]]:
        while True:
            data = self.sock.recv(1 << 20)
            if not data:
                return
            self.reader.feed(data)
            yield from self.reader.frames()


def stamp(t_ns: int) -> rospy.Time:
    return rospy.Time(int(t_ns // 1_000_000_000), int(t_ns % 1_000_000_000))


def run_robot(args: argparse.Namespace, link: Link) -> None:
    def on_image(msg: Image) -> None:
        t = msg.header.stamp.to_nsec()
        link.send(wire.image(t, msg.height, msg.width, msg.step, msg.encoding, bytes(msg.data)))

    def on_imu(msg: Imu) -> None:
        w, a = msg.angular_velocity, msg.linear_acceleration
        link.send(wire.imu(msg.header.stamp.to_nsec(), (w.x, w.y, w.z), (a.x, a.y, a.z)))

    odom = rospy.Publisher(args.odom_topic, Odometry, queue_size=100)
    tf = tf2_ros.TransformBroadcaster()
    placement_tf = tf2_ros.StaticTransformBroadcaster()  # latched: changes only with the cloud
    rospy.Subscriber(args.image_topic, Image, on_image, queue_size=20, buff_size=1 << 25)
    rospy.Subscriber(args.imu_topic, Imu, on_imu, queue_size=2000)
    link.send(wire.frame(wire.READY, b""))
    for kind, payload in link.frames():
        if kind == wire.PLACEMENT:
            _global_map, _map_id, p, q = wire.read_placement(payload)
            place = TransformStamped()
            place.header.stamp = rospy.Time.now()
            place.header.frame_id = args.global_frame
            place.child_frame_id = args.map_frame
            tr, rot = place.transform.translation, place.transform.rotation
            tr.x, tr.y, tr.z = p
            rot.x, rot.y, rot.z, rot.w = q
            placement_tf.sendTransform(place)
            continue
        if kind != wire.POSE:
            continue
        t, _map_id, _status, p, q = wire.read_pose(payload)
        msg = Odometry()
        msg.header.stamp = stamp(t)
        msg.header.frame_id = args.map_frame
        msg.child_frame_id = args.base_frame
        pos, ori = msg.pose.pose.position, msg.pose.pose.orientation
        pos.x, pos.y, pos.z = p
        ori.x, ori.y, ori.z, ori.w = q
        odom.publish(msg)
        tfm = TransformStamped()
        tfm.header = msg.header
        tfm.child_frame_id = args.base_frame
        tr, rot = tfm.transform.translation, tfm.transform.rotation
        tr.x, tr.y, tr.z = p
        rot.x, rot.y, rot.z, rot.w = q
        tf.sendTransform(tfm)


def run_player(args: argparse.Namespace, link: Link) -> None:
    images = rospy.Publisher(args.image_topic, Image, queue_size=20)
    imus = rospy.Publisher(args.imu_topic, Imu, queue_size=2000)
    rospy.Subscriber(
        args.odom_topic, Odometry, lambda m: link.send(wire.odom(m.header.stamp.to_nsec()))
    )
    deadline = rospy.get_time() + 30.0
    while (images.get_num_connections() == 0 or imus.get_num_connections() == 0) and (
        rospy.get_time() < deadline and not rospy.is_shutdown()
    ):
        rospy.sleep(0.05)
    link.send(wire.frame(wire.READY, b""))
    for kind, payload in link.frames():
        if kind == wire.IMU:
            t, g, a = wire.read_imu(payload)
            m = Imu()
            m.header.stamp = stamp(t)
            m.header.frame_id = "imu"
            m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z = g
            m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z = a
            imus.publish(m)
        elif kind == wire.IMAGE:
            t, h, w, step, enc, data = wire.read_image(payload)
            im = Image()
            im.header.stamp = stamp(t)
            im.header.frame_id = "cam0"
            im.height, im.width, im.step, im.encoding, im.data = h, w, step, enc, data
            images.publish(im)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python3 -m services.robot.ros1.bridge")
    p.add_argument("--mode", choices=("robot", "player"), required=True)
    p.add_argument("--socket", required=True)
    p.add_argument("--image-topic", required=True)
    p.add_argument("--imu-topic", required=True)
    p.add_argument("--odom-topic", default="odom")
    p.add_argument("--map-frame", default="map")
    p.add_argument("--global-frame", default="world")
    p.add_argument("--base-frame", default="base_link")
    p.add_argument("--node-name", default="recslam_robot")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    rospy.init_node(args.node_name, anonymous=True, disable_signals=True)
    link = Link(args.socket)
    try:
        (run_robot if args.mode == "robot" else run_player)(args, link)
    except (BrokenPipeError, ConnectionResetError):
        pass
    finally:
        rospy.signal_shutdown("socket closed")
    return 0


if __name__ == "__main__":
    sys.exit(main())

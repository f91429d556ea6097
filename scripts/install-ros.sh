#!/bin/sh
# Install Debian's ROS 1 (roscore, rospy and the sensor_msgs / nav_msgs / tf2 messages) for the
# live-robot test and `recslam robot --source ros1` (idempotent, quiet, fast when installed).
# Only acts when running as root with apt-get; otherwise the ROS test skips and says why.
set -eu
PACKAGES="ros-core python3-rospy python3-sensor-msgs python3-nav-msgs python3-tf2-ros python3-geometry-msgs"
if command -v roscore >/dev/null 2>&1 && [ -x /usr/bin/python3 ] &&
    /usr/bin/python3 -c "import rospy, tf2_ros, nav_msgs.msg, sensor_msgs.msg" 2>/dev/null; then
    exit 0
fi
if [ "$(id -u)" != "0" ]; then
    echo "install-ros: ROS 1 missing and not root; the live ROS test will skip" >&2
    exit 0
fi
if ! command -v apt-get >/dev/null 2>&1; then
    echo "install-ros: no apt-get here; the live ROS test will skip" >&2
    exit 0
fi
export DEBIAN_FRONTEND=noninteractive
# shellcheck disable=SC2086
if ! apt-get install -y -qq --no-install-recommends $PACKAGES >/dev/null 2>&1; then
    apt-get update -qq >/dev/null
    # shellcheck disable=SC2086
    apt-get install -y -qq --no-install-recommends $PACKAGES >/dev/null
fi

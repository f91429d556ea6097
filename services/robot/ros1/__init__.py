"""ROS 1 in and out, fenced here (OpenVINS keeps its ROS code in one folder the same way).

``rospy`` lives in Debian's ``/usr/bin/python3`` (``python3-rospy``), not in the project's
virtual environment, so the ROS side runs as a process of its own:
:mod:`services.robot.ros1.bridge` (the only module that imports ``rospy``) subscribes to the
camera and IMU topics and publishes ``nav_msgs/Odometry`` and TF, and talks to the robot over
a local socket in the framing of :mod:`services.robot.ros1.wire` (stdlib only, shared by both
ends). :mod:`services.robot.ros1.source` is the robot's end (``recslam robot --source ros1``):
it starts the bridge and feeds a :class:`~services.robot.client.RobotClient`.
"""

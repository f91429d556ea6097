"""Shared data readers and generators: the EuRoC ASL layout (EuRoC, TUM-VI, the synthetic
multi-robot set), calibration files (EuRoC ``sensor.yaml``, Kalibr), and ROS bags."""

"""ros2 launch home_robot_bringup slam_sim_camera.launch.py — node set 'slam_sim_camera' of config/nodesets.yaml."""

import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from nodeset_launch_common import nodeset_launch_description  # noqa: E402


def generate_launch_description():
    return nodeset_launch_description("slam_sim_camera")

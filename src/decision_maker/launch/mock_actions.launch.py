"""ros2 launch decision_maker mock_actions.launch.py — the simulated hardware (the seed's command).

The nodes and parameters come from home_robot_bringup's node set ``mock_actions``
(config/nodesets.yaml + config/params/sim.yaml): one source of truth.
"""

import os
import sys

from ament_index_python.packages import get_package_share_directory

sys.path.insert(0, os.path.join(get_package_share_directory("home_robot_bringup"), "launch"))
from nodeset_launch_common import nodeset_launch_description  # noqa: E402


def generate_launch_description():
    return nodeset_launch_description("mock_actions")

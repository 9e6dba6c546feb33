"""Repository-wide pytest setup: the ROS test fixtures (real processes, unique domains)."""

pytest_plugins = ["home_robot_bringup.testing"]

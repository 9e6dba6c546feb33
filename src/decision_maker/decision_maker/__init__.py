"""The robot's brain (see README): command inputs, scenario library, execution engine and the
simulated hardware servers. Pure logic modules import no rclpy; ``*_node.py``/``mock_*`` are the
ROS shells."""

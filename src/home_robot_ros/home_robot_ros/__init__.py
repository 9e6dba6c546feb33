"""rclpy helpers shared by the home robot's nodes.

Modules:
    actions -- ``ActionClient``: rclpy's action client without the reply-before-request race.
    poses -- ``pose_to_matrix``: a geometry_msgs pose as a checked [4, 4] matrix.
"""

"""rclpy helpers shared by the home robot's nodes.

Modules:
    actions -- ``ActionClient``: rclpy's action client without the reply-before-request race.
    poses -- ``pose_to_matrix``: a geometry_msgs pose as a checked [4, 4] matrix.
    startup -- ``CONFIG_ERRORS``: what a node's constructor raises for a bad parameter (a ``main()`` exits 2).
"""

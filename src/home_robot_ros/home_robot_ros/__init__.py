"""rclpy helpers shared by the home robot's nodes.

Modules:
    actions -- ``ActionClient``: rclpy's action client without the reply-before-request race.
"""

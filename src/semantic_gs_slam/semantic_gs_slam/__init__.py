"""Semantic Gaussian-splatting RGB-D SLAM engine (pure Python/PyTorch, no rclpy).

Reserved by the foundation; the SLAM-core issue fills it."""

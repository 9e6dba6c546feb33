"""Semantic object database over a semantic Gaussian-splatting map.

Pure logic (no rclpy) lives in :mod:`object_query.semantic_map`; the ROS shell is
:mod:`object_query.object_query_server` and :mod:`object_query.object_query_client`.
"""

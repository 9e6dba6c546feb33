"""ROS 2 streaming wrapper (``run_gs_slam_server`` / ``run_gs_slam_client``) around
:mod:`semantic_gs_slam`. Reserved by the foundation; the SLAM-streaming issue fills it."""

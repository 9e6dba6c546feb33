"""rclpy helpers shared by the home robot's nodes.

Modules:
    actions -- ``ActionClient``: rclpy's action client without the reply-before-request race.
    poses -- ``pose_to_matrix``: a geometry_msgs pose as a checked [4, 4] matrix.
    spinning -- ``spin``: an executor that goes on when another thread destroyed an entity while it built its wait
        set (rclpy's ``InvalidHandle`` race, which ended the SLAM server after a run).
    startup -- starting a node: ``build_node`` / ``spin_node`` (a node that cannot start says why, exit code 2),
        ``read_once`` (parameters read at start, a later change refused), ``number_in``, ``action_name``.
"""

"""The simulated robot behind the mock Nav2 and grasp servers.

* :mod:`.world` — the kinematic world (no ROS): a base that drives, a gripper, objects.
* :mod:`.actions` — the action-server plumbing the simulated servers share (goals driven by a timer).
"""

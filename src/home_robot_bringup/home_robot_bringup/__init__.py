"""Bring-up of the home robot: node sets + parameters as YAML (the one source of truth),
``ros2 launch`` files, and a launcher/supervisor for machines without ros2cli/launch_ros.

Modules:
    nodeset  -- pure: read ``config/nodesets.yaml`` into :class:`NodeSpec` lists.
    process  -- supervised node processes (prefixed, coloured logs; clean shutdown).
    domain   -- leases of unique ROS_DOMAIN_IDs (tests, demo).
    launcher -- the ``launch`` command line.
    testing  -- pytest plugin: real node processes per test on a unique domain.
"""

"""Executing plans: the engine (no ROS), the robot port that drives Nav2 and the manipulation actions, the
exploration gate.

* :mod:`.engine` — :class:`~decision_maker.execution.engine.ExecutionEngine`: queue, run, cancel, status.
* :mod:`.ros_robot` — the engine's robot port over ROS actions.
* :mod:`.repeated_calls` — :class:`~decision_maker.execution.repeated_calls.AnswerMemory`: a retried ``submit_command``
  call answered once.
* :mod:`.stage0` — the gate that holds commands while the robot explores its home.
"""

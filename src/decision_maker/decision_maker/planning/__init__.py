"""Planning helpers beside the seed's :mod:`decision_maker.nl_planner` (no ROS).

* :mod:`.llm_planner` — the LLM planner behind the same planner seam.
* :mod:`.approach` — where the robot stands to reach an object.
* :mod:`.stop_words` — which spoken or typed words stop the robot at once.
"""

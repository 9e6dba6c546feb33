"""Loop closure: detection by registering a keyframe against old overlapping ones, and the pose graph.

* :mod:`.detection` — candidate keyframes, registration and the verdict on a loop.
* :mod:`.posegraph` — the SE(3) pose graph and its optimisation.
* :mod:`.closing` — the engine's loop-closing step (adds loops to the graph, moves poses and Gaussians).
"""

from semantic_gs_slam import _moved

__getattr__ = _moved.forward(__name__)  # the old module semantic_gs_slam.loop: its names, for one release

"""The synthetic home: rendered RGB-D frames with ground truth, and the demo map built from them.

* :mod:`.scenes` — the scene and its frames (``python -m semantic_gs_slam.synthetic --out DIR``).
* :mod:`.demo_map` — the map ``make demo`` queries (``python -m semantic_gs_slam.synthetic.demo_map``).
"""

from semantic_gs_slam import _moved

__getattr__ = _moved.forward(__name__)  # the old module semantic_gs_slam.synthetic: its names, for one release

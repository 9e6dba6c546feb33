"""Camera tracking: point-to-plane ICP against the depth rendered from the map, then photometric refinement.

* :mod:`.tracker` — the tracking (the PyTorch reference of every step).
* :mod:`.icp_numba` — the compiled CPU ICP step (numba); its kernel in :mod:`.numba_kernels`.
"""

from semantic_gs_slam import _moved

__getattr__ = _moved.forward(__name__)  # the old module semantic_gs_slam.tracking: its names, for one release

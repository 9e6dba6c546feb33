"""Frames in: dataset loaders, colour registered to depth, exposure.

* :mod:`.datasets` — the recording layouts the engine reads (Replica, TUM RGB-D, 7-Scenes ...).
* :mod:`.colour_registration` — a second colour camera registered to the depth camera.
* :mod:`.calibrate_colour` — its command (``python -m semantic_gs_slam.io.calibrate_colour DATASET``).
* :mod:`.degrade` — a recording made harder (noisier depth, motion blur) for the benchmarks.
* :mod:`.exposure` — per-frame exposure (gain and offset) against the map.
* :mod:`.host_frame` — a camera frame checked and converted on the host (NumPy, and one compiled call:
  :mod:`.host_frame_numba`).
"""

"""The compiled twin of :func:`semantic_gs_slam.io.host_frame.host_frame_reference` (numba, ``nogil=True``)."""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["host_frame"]


@numba.njit(cache=True, nogil=True)
def host_frame(rgb, depth, divide, depth_min, depth_max, rgb_out, depth_out):
    """rgb [H, W, 3] and depth [H, W] (any numeric type) to float32 rgb_out (divided by 255 when ``divide``, in
    float32 as NumPy does) and depth_out (0 outside [depth_min, depth_max], float32 bounds). Returns the counts
    (colour values not finite, depth values not finite, negative depths, depths in range)."""
    nonfinite_rgb = 0
    nonfinite_depth = 0
    negative = 0
    valid = 0
    for y in range(depth.shape[0]):
        for x in range(depth.shape[1]):
            for ch in range(3):
                v = np.float32(rgb[y, x, ch])
                if divide:
                    v = v / np.float32(255.0)
                if not np.isfinite(v):
                    nonfinite_rgb += 1
                rgb_out[y, x, ch] = v
            d = np.float32(depth[y, x])
            if not np.isfinite(d):
                nonfinite_depth += 1
            elif d < 0:
                negative += 1
            if d >= depth_min and d <= depth_max:
                valid += 1
                depth_out[y, x] = d
            else:
                depth_out[y, x] = np.float32(0.0)
    return nonfinite_rgb, nonfinite_depth, negative, valid

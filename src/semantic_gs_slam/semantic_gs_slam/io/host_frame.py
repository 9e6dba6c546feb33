"""A camera frame checked and converted on the host: what :meth:`~semantic_gs_slam.slam.SLAM.add_frame` takes in
with the keyframe front end, before anything reaches the device.

:func:`host_frame` refuses a frame with NaN or infinite colour or depth, negative depth or almost no depth in range,
and returns float32 copies: colour in [0, 1] (``uint8`` divided by 255), depth in metres with 0 outside the range.
Two paths, the same result bit for bit: NumPy (:func:`host_frame_reference`, the reference) and one compiled call
(:func:`semantic_gs_slam.io.host_frame_numba.host_frame`). The compiled one lets the GIL go once per frame instead of
once per NumPy operation: beside a thread that keeps the GIL (a mapping thread launching GPU kernels, a ROS
executor's callbacks), each of those waits up to the interpreter's switch interval to get it back
(``bench/frontend_gil.py``).
"""

from __future__ import annotations

import functools

import numpy as np

from semantic_gs_slam.devices import numba_available
from semantic_gs_slam.errors import FrameError

__all__ = ["check_counts", "host_frame", "host_frame_reference"]


@functools.cache
def _fast():
    from semantic_gs_slam.io import host_frame_numba

    return host_frame_numba


def check_counts(nonfinite_rgb: int, nonfinite_depth: int, negative: int, valid: int, pixels: int,
                 depth_min: float, depth_max: float) -> None:
    """Refuse a frame by its counts (colour and depth values not finite, negative depths, depths in range of
    ``pixels``): FrameError with what is wrong, first match in that order."""
    if nonfinite_rgb:
        raise FrameError("rgb contains NaN or inf")
    if nonfinite_depth:
        raise FrameError(f"depth contains {nonfinite_depth} NaN/inf values (use 0 for missing)")
    if negative:
        raise FrameError("depth has negative values")
    frac = valid / max(pixels, 1)
    if frac < 0.05:
        raise FrameError(f"only {frac * 100:.1f} % of depth pixels are valid "
                         f"(in [{depth_min}, {depth_max}] m); is the depth in metres?")


def host_frame_reference(rgb: np.ndarray, depth: np.ndarray, depth_min: float, depth_max: float
                         ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`host_frame` in NumPy operations (the reference)."""
    try:
        rgb_f = rgb.astype(np.float32) / 255.0 if rgb.dtype == np.uint8 else rgb.astype(np.float32)
        depth_f = depth.astype(np.float32)
    except (TypeError, ValueError) as exc:
        raise FrameError(f"frame arrays must be numeric: {exc}") from exc
    finite = np.isfinite(depth_f)
    valid = (depth_f >= np.float32(depth_min)) & (depth_f <= np.float32(depth_max))
    check_counts(int((~np.isfinite(rgb_f)).sum()), int((~finite).sum()), int((depth_f[finite] < 0).sum()),
                 int(valid.sum()), depth_f.size, depth_min, depth_max)
    depth_f[~valid] = 0.0
    return rgb_f, depth_f


def host_frame(rgb: np.ndarray, depth: np.ndarray, depth_min: float, depth_max: float, fast: bool | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """Check and convert one frame.

    Args:
        rgb: [H, W, 3] colour, ``uint8`` (0..255) or any other numeric type (taken as [0, 1]).
        depth: [H, W] metres, any numeric type (0: missing).
        depth_min, depth_max: metres; depth outside is set to 0.
        fast: the compiled path (None: when numba is installed and both arrays are numeric).

    Returns:
        rgb [H, W, 3] float32 in [0, 1] and depth [H, W] float32, new arrays.

    Raises:
        FrameError: non-numeric arrays, NaN or infinite colour or depth, negative depth, or fewer than 5 % of the
            pixels with depth in range.
    """
    rgb, depth = np.asarray(rgb), np.asarray(depth)
    numeric = rgb.dtype.kind in "buif" and depth.dtype.kind in "buif"
    if fast is None:
        fast = numeric and numba_available()
    if not fast or not numeric or rgb.shape != depth.shape + (3,):
        return host_frame_reference(rgb, depth, depth_min, depth_max)
    rgb_f = np.empty(rgb.shape, np.float32)
    depth_f = np.empty(depth.shape, np.float32)
    counts = _fast().host_frame(rgb, depth, rgb.dtype == np.uint8, np.float32(depth_min), np.float32(depth_max),
                                rgb_f, depth_f)
    check_counts(*counts, depth.size, depth_min, depth_max)
    return rgb_f, depth_f

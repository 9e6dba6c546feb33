"""A camera frame checked and converted on the host: the compiled call against the NumPy reference, and the errors."""

from __future__ import annotations

import numpy as np
import pytest

from semantic_gs_slam.devices import numba_available
from semantic_gs_slam.errors import FrameError
from semantic_gs_slam.io.host_frame import host_frame, host_frame_reference

needs_numba = pytest.mark.skipif(not numba_available(), reason="numba not installed")


def _frame(rgb_dtype, depth_dtype, seed=0):
    rng = np.random.default_rng(seed)
    h, w = 31, 45
    if rgb_dtype == np.uint8:
        rgb = rng.integers(0, 256, (h, w, 3)).astype(np.uint8)
    else:
        rgb = rng.random((h, w, 3)).astype(rgb_dtype)
    depth = rng.random((h, w)) * 12.0  # some above depth_max, some below depth_min
    depth[rng.random((h, w)) < 0.1] = 0.0
    if depth_dtype == np.uint16:  # millimetres as stored: the caller scales; here the raw integer metres check
        depth = np.round(depth).astype(np.uint16)
    else:
        depth = depth.astype(depth_dtype)
    depth.flat[7] = np.float32(0.1) if depth_dtype != np.uint16 else 0  # exactly at depth_min (float32)
    return rgb, depth


@needs_numba
@pytest.mark.parametrize("rgb_dtype", [np.uint8, np.float32, np.float64])
@pytest.mark.parametrize("depth_dtype", [np.float32, np.float64, np.uint16])
def test_the_compiled_call_gives_the_reference_bit_for_bit(rgb_dtype, depth_dtype):
    rgb, depth = _frame(rgb_dtype, depth_dtype)
    a_rgb, a_depth = host_frame(rgb, depth, 0.1, 10.0, fast=True)
    b_rgb, b_depth = host_frame_reference(rgb, depth, 0.1, 10.0)
    assert a_rgb.dtype == a_depth.dtype == np.float32
    np.testing.assert_array_equal(a_rgb, b_rgb)
    np.testing.assert_array_equal(a_depth, b_depth)
    assert 0.0 < (a_depth == 0).mean() < 0.5 and a_depth.max() <= 10.0
    assert a_rgb.max() <= 1.0 and a_rgb is not rgb


@pytest.mark.parametrize("fast", [False, pytest.param(True, marks=needs_numba)])
def test_bad_frames_get_the_same_clear_errors_on_both_paths(fast):
    rgb, depth = _frame(np.float32, np.float32)
    bad = rgb.copy()
    bad[0, 0, 1] = np.nan
    with pytest.raises(FrameError, match="rgb contains NaN or inf"):
        host_frame(bad, depth, 0.1, 10.0, fast=fast)
    bad = depth.copy()
    bad[1, 1] = np.inf
    bad[2, 2] = np.nan
    with pytest.raises(FrameError, match="depth contains 2 NaN/inf values"):
        host_frame(rgb, bad, 0.1, 10.0, fast=fast)
    bad = depth.copy()
    bad[3, 3] = -1.0
    with pytest.raises(FrameError, match="negative"):
        host_frame(rgb, bad, 0.1, 10.0, fast=fast)
    with pytest.raises(FrameError, match=r"only 0\.0 % of depth pixels are valid"):
        host_frame(rgb, depth * 1000.0, 0.1, 10.0, fast=fast)  # millimetres given as metres


def test_non_numeric_arrays_are_refused_by_the_reference():
    rgb, depth = _frame(np.float32, np.float32)
    with pytest.raises(FrameError, match="numeric"):
        host_frame(np.full(rgb.shape, "red"), depth, 0.1, 10.0)

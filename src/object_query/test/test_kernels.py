"""The compiled per-bin sums agree with the numpy reference (the fast path must never change answers)."""

import numpy as np
import pytest

from object_query.kernels import bin_sums, bin_sums_numpy, have_fast_path

pytestmark = pytest.mark.skipif(not have_fast_path(), reason="numba not installed (the numpy reference is used)")


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_fast_path_matches_reference(dtype):
    rng = np.random.default_rng(1)
    n, size = 50_000, 37
    bins = rng.integers(-3, size + 5, n)  # includes ignored out-of-range bins
    means = (rng.normal(0, 10, (n, 3))).astype(dtype)
    c_ref, s_ref = bin_sums_numpy(bins, means, size)
    c_fast, s_fast = bin_sums(bins, means, size, fast=True)
    assert np.array_equal(c_ref, c_fast) and c_ref.sum() == np.count_nonzero((bins >= 0) & (bins < size))
    np.testing.assert_allclose(s_fast, s_ref, rtol=1e-9, atol=1e-6)


def test_automatic_choice_and_bad_shapes():
    bins = np.array([0, 1, 1, 5])
    means = np.arange(12, dtype=np.float64).reshape(4, 3)
    counts, sums = bin_sums(bins, means, 3)  # small: reference; bin 5 ignored
    assert counts.tolist() == [1, 2, 0] and sums[1].tolist() == [9.0, 11.0, 13.0]
    with pytest.raises(ValueError, match="need bins"):
        bin_sums(bins, means[:, :2], 3)

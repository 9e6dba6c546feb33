"""Per-bin point counts and coordinate sums — the O(N) core of the class centroids.

Two implementations with one contract (:func:`bin_sums_numpy` is the reference, tested against
the fast path): numpy's ``bincount`` (four passes over the points plus dtype conversions, ~200 ms
for 10 M points here) and, when ``numba`` is installed, one fused compiled pass (~40-60 ms). The
fast path is optional: without numba (e.g. with a system ROS 2 whose numpy numba does not
support) everything works on the reference.
"""

from __future__ import annotations

import functools
import importlib.util

import numpy as np

#: Below this many points the compiled kernel is not worth its (cached) start-up.
FAST_PATH_MIN_POINTS = 200_000


def bin_sums_numpy(bins: np.ndarray, means: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Reference: counts and coordinate sums per bin.

    Args:
        bins: [N] integer bin of each point; values outside ``[0, size)`` are ignored.
        means: [N, 3] float32/float64 coordinates.
        size: number of bins.

    Returns:
        counts [size] int64, sums [size, 3] float64.
    """
    b = np.asarray(bins, dtype=np.intp)
    keep = (b >= 0) & (b < size)
    if not keep.all():
        b = np.where(keep, b, size)
    counts = np.bincount(b, minlength=size + 1)[:size].astype(np.int64)
    sums = np.stack([np.bincount(b, weights=means[:, a], minlength=size + 1)[:size] for a in range(3)], 1)
    return counts, sums


@functools.cache
def _compiled():  # pragma: no cover - compiled
    """The numba kernel, built on first use (importing numba costs ~0.4 s: only for big maps)."""
    import numba

    @numba.njit(cache=True, nogil=True)
    def bin_sums_compiled(bins, means, size):
        counts = np.zeros(size, np.int64)
        sums = np.zeros((size, 3), np.float64)
        for i in range(bins.shape[0]):
            b = bins[i]
            if 0 <= b < size:
                counts[b] += 1
                sums[b, 0] += means[i, 0]
                sums[b, 1] += means[i, 1]
                sums[b, 2] += means[i, 2]
        return counts, sums

    return bin_sums_compiled


@functools.cache
def have_fast_path() -> bool:
    """Whether numba is installed (without importing it)."""
    return importlib.util.find_spec("numba") is not None


def bin_sums(bins: np.ndarray, means: np.ndarray, size: int, fast: bool | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
    """Counts [size] and sums [size, 3] per bin (see :func:`bin_sums_numpy`).

    Args:
        fast: True = the compiled kernel (error if numba is missing), False = the numpy reference,
            None = compiled when available and the map is large enough.
    """
    if means.ndim != 2 or means.shape[1] != 3 or len(bins) != len(means):
        raise ValueError(f"need bins [N] and means [N, 3], got {bins.shape} and {means.shape}")
    if fast is None:
        fast = len(bins) >= FAST_PATH_MIN_POINTS and have_fast_path()
    if not fast:
        return bin_sums_numpy(bins, means, size)
    if not have_fast_path():
        raise RuntimeError("the compiled kernel needs numba (pip install numba)")
    m = means if means.dtype in (np.float32, np.float64) else means.astype(np.float64)
    return _compiled()(np.ascontiguousarray(bins), np.ascontiguousarray(m), int(size))


#: Points per chunk of :func:`bin_sums_chunked`: a chunk's ids, coordinates and float64 copies stay in cache.
CHUNK_POINTS = 1 << 17


def bin_sums_chunked(ids: np.ndarray, means: np.ndarray, lo: int, size: int, valid_fn=None,  # noqa: ANN001
                     chunk: int = CHUNK_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """Counts and sums per bin in one pass over cache-sized chunks (numpy only, no compile step).

    The start-up path: numba's import and cache load cost 0.5-3 s on a busy machine, more than
    the whole pass. Each chunk is read once from memory; bin offset, range check, validity and
    the four ``bincount`` passes then run on data in cache.

    Args:
        ids: [N] integer ids; bin = ``id - lo``; bins outside ``[0, size)`` are ignored.
        means: [N, 3] float coordinates.
        lo: id of bin 0.
        size: number of bins.
        valid_fn: ``valid_fn(start, stop) -> [stop - start] bool`` (points to use), or None (all).
        chunk: points per chunk.

    Returns:
        counts [size] int64, sums [size, 3] float64 (equal to :func:`bin_sums_numpy` of the same bins).
    """
    if means.ndim != 2 or means.shape[1] != 3 or len(ids) != len(means):
        raise ValueError(f"need ids [N] and means [N, 3], got {ids.shape} and {means.shape}")
    if chunk < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    dump = size  # one extra bin collects what is ignored
    counts = np.zeros(size + 1, np.int64)
    sums = np.zeros((3, size + 1), np.float64)
    for start in range(0, len(ids), chunk):
        stop = min(start + chunk, len(ids))
        b = ids[start:stop].astype(np.intp)  # [n]
        if lo:
            b -= lo
        bad = (b < 0) | (b >= size)
        if valid_fn is not None:
            bad |= ~valid_fn(start, stop)
        if bad.any():
            b[bad] = dump
        counts += np.bincount(b, minlength=size + 1)
        m = means[start:stop]  # [n, 3]
        for a in range(3):
            sums[a] += np.bincount(b, weights=m[:, a], minlength=size + 1)
    return counts[:size], sums[:, :size].T.copy()

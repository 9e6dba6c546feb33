"""A recording made harder, to test tracking on what a worse camera would give (NumPy, no ROS).

* Depth noise: a structured-light sensor's axial noise grows with the square of the depth; a Kinect v1's is
  about ``0.0012 + 0.0019 (z - 0.4)^2`` metres (Nguyen, Izadi and Lovell, 3DIMPVT 2012). :func:`noisy_depth` adds
  ``scale`` times that, independently per pixel and frame (seeded by the frame's index: repeatable).
* Motion blur: :class:`DegradedDataset` averages each frame's colour with the ``blur`` frames on either side of it
  in the recording (a longer exposure of the same motion).
* Exposure swings: :class:`DegradedDataset` multiplies frame i's colour by ``1 + gain sin(2 pi i / gain_period)``
  (clipped to [0, 1]): an auto-exposure that keeps changing its mind, brighter and darker than the recording.
* Depth dropouts: :class:`DegradedDataset` drops ``holes`` of the depth pixels at random, independently per pixel and
  frame (seeded by the frame's index): a speckled time-of-flight or stereo camera, where a structured-light one
  leaves holes in regions.
* Dropped frames: :func:`drop_frames` leaves out frames of a sequence at random (a stream that drops them unevenly).
* Unsynchronised colour: :class:`DegradedDataset` gives frame i the colour of recorded frame ``i + colour_lag``
  (the last frame's near the end): a camera whose colour shutter does not fire with its depth, so that a moving
  camera's colour sits off its depth by the motion in between (TUM RGB-D's Kinect: up to ~20 ms).

Usage::

    ds = DegradedDataset(load_dataset(path), depth_noise=2.0, blur=1, gain=0.3, holes=0.3)   # any Dataset
"""

from __future__ import annotations

import math

import numpy as np

from semantic_gs_slam.io.datasets import Dataset, Frame


def kinect_axial_noise(depth: np.ndarray) -> np.ndarray:
    """A Kinect v1's axial noise (m, one standard deviation) at ``depth`` [...] metres."""
    return 0.0012 + 0.0019 * (depth - 0.4) ** 2


def noisy_depth(depth: np.ndarray, scale: float, seed: int) -> np.ndarray:
    """``depth`` [H, W] metres (0: none) plus ``scale`` x :func:`kinect_axial_noise`; missing pixels stay 0."""
    rng = np.random.default_rng(seed)
    noise = rng.standard_normal(depth.shape) * (scale * kinect_axial_noise(depth))
    return np.where(depth > 0, np.maximum(depth + noise, 0.0), 0.0).astype(depth.dtype)


def drop_frames(frames: list[int] | range, p: float, seed: int = 20261128) -> list[int]:
    """``frames`` with each but the first left out with probability ``p`` in [0, 1) (seeded: the same frames every
    run): a stream that drops frames unevenly."""
    if not 0 <= p < 1:
        raise ValueError(f"the fraction of frames dropped must be in [0, 1), got {p!r}")
    keep = np.random.default_rng(seed).random(len(frames)) >= p
    keep[0] = True
    return [i for i, k in zip(frames, keep, strict=True) if k]


class DegradedDataset:
    """A :class:`~semantic_gs_slam.io.datasets.Dataset` whose frames have noisier depth and blurred colour.

    Args:
        base: the recording.
        depth_noise: times a Kinect v1's axial noise added to the depth (>= 0; 0: none).
        blur: colour averaged over the frames ``i - blur .. i + blur`` of the recording (>= 0; 0: none).
        gain: the exposure swing: frame i's colour times ``1 + gain sin(2 pi i / gain_period)`` (in [0, 1); 0:
            none). gain_period: frames of the recording per swing (> 0; 60: 2 s of a 30-Hz camera).
        holes: the fraction of depth pixels dropped (set to 0) at random (in [0, 1); 0: none).
        colour_lag: frame i's colour is taken from recorded frame ``i + colour_lag`` (clamped to the recording;
            may be negative; 0: none), before blur and exposure.
    """

    def __init__(self, base: Dataset, depth_noise: float = 0.0, blur: int = 0, gain: float = 0.0,
                 gain_period: float = 60.0, holes: float = 0.0, colour_lag: int = 0) -> None:
        if not (math.isfinite(depth_noise) and depth_noise >= 0):
            raise ValueError(f"depth_noise must be a finite number >= 0, got {depth_noise!r}")
        if blur < 0:
            raise ValueError(f"blur must be >= 0, got {blur!r}")
        if not 0 <= gain < 1:
            raise ValueError(f"gain must be in [0, 1), got {gain!r}")
        if not (math.isfinite(gain_period) and gain_period > 0):
            raise ValueError(f"gain_period must be a finite number > 0, got {gain_period!r}")
        self.base, self.depth_noise, self.blur = base, float(depth_noise), int(blur)
        if not 0 <= holes < 1:
            raise ValueError(f"holes must be in [0, 1), got {holes!r}")
        self.gain, self.gain_period, self.holes = float(gain), float(gain_period), float(holes)
        if int(colour_lag) != colour_lag:
            raise ValueError(f"colour_lag must be a whole number of frames, got {colour_lag!r}")
        self.colour_lag = int(colour_lag)

    def __getattr__(self, name: str):  # intrinsics, poses, sem_paths, camera_line(), ... are the recording's
        return getattr(self.base, name)

    def __len__(self) -> int:
        return len(self.base)

    def __getitem__(self, i: int) -> Frame:
        f = self.base[i]
        i = f.index
        if self.colour_lag:
            f.rgb = self._colour(i + self.colour_lag)
        if self.blur:
            near = [self._colour(j + self.colour_lag)
                    for j in range(max(0, i - self.blur), min(len(self.base), i + self.blur + 1)) if j != i]
            f.rgb = np.mean([f.rgb, *near], axis=0).astype(f.rgb.dtype)
        if self.depth_noise:
            f.depth = noisy_depth(f.depth, self.depth_noise, seed=i)
        if self.gain:
            g = 1.0 + self.gain * math.sin(2.0 * math.pi * i / self.gain_period)
            f.rgb = np.clip(f.rgb * g, 0.0, 1.0).astype(f.rgb.dtype)
        if self.holes:
            drop = np.random.default_rng(1_000_003 + i).random(f.depth.shape) < self.holes  # not the noise's stream
            f.depth = np.where(drop, 0.0, f.depth).astype(f.depth.dtype)
        return f

    def _colour(self, j: int) -> np.ndarray:
        """[H, W, 3] the colour of recorded frame ``j``, clamped to the recording."""
        return self.base[min(max(j, 0), len(self.base) - 1)].rgb

    def describe(self) -> str:
        """One line for logs: what was done to the frames."""
        swing = f"exposure swinging by ±{100 * self.gain:g} % every {self.gain_period:g} frames"
        parts = ([f"depth noise {self.depth_noise:g} x a Kinect v1's"] if self.depth_noise else []) + \
            ([f"colour averaged over {2 * self.blur + 1} frames"] if self.blur else []) + \
            ([swing] if self.gain else []) + \
            ([f"{100 * self.holes:g} % of the depth pixels dropped at random"] if self.holes else []) + \
            ([f"colour from {self.colour_lag:+d} recorded frames"] if self.colour_lag else [])
        return ", ".join(parts) or "none"

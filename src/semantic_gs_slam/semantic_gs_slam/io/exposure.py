"""Per-frame exposure: a real camera's auto-exposure and white balance change its colours frame to frame.

The map keeps colours in one reference exposure (the first frame's). Each later frame's exposure relative
to the map is a per-channel gain, ``live = gain * map`` (the bias slot of the [2, 3] result stays 0). It is
fitted on the map rendered at the frame's tracked pose (the render densification makes anyway), on pixels
the map covers and the frame measured depth for, leaving out clipped values. The frame's colour is brought
into the map's exposure (:func:`to_map`) before it seeds or optimises Gaussians, and renders are put back
into the frame's exposure (:func:`to_frame`) for evaluation.

The gain is the ratio of the two images' per-channel means on that full-size render. Alternatives tried:
- A regression's gain shrinks toward 0 when the render is a little misaligned (not measured: the reason
  it was not built).
- Measured on the synthetic home, where the exposure never changes, with the tracking render (shrunk
  Gaussians covering 6-8 % of the image opaquely):
  - Matched means and standard deviations: -0.8 dB of PSNR.
  - The ratio of means: -1.2 dB, and the gain crept to 0.90 in blue within 20 frames.
On the full render the gains stay within 1 % of 1.

Pure torch on the engine's device, fixed shapes, no host synchronisation; no ROS.
"""

from __future__ import annotations

import torch
from torch import Tensor

IDENTITY = ((1.0, 1.0, 1.0), (0.0, 0.0, 0.0))
SATURATED = 0.98  # live values at or above this are clipped by the sensor: left out of the fit


def identity(device: torch.device | str = "cpu") -> Tensor:
    """[2, 3]: gain 1, bias 0."""
    return torch.tensor(IDENTITY, dtype=torch.float32, device=device)


def fit(render_rgb: Tensor, silhouette: Tensor, live_rgb: Tensor, live_depth: Tensor, min_silhouette: float = 0.95,
        min_pixels: int = 500, gain_range: tuple[float, float] = (0.5, 2.0), dead_band: float = 0.05) -> Tensor:
    """The frame's exposure relative to the map: [2, 3] (gain, bias) per channel, ``live = gain * map + bias``.

    Args:
        render_rgb: [H, W, 3] the map rendered near the frame's pose. silhouette: [H, W] its opacity.
        live_rgb: [H, W, 3] the frame's colour in [0, 1]. live_depth: [H, W] metres (0: missing).
        min_silhouette: pixels the map covers at least this much are used ...
        min_pixels: ... and with fewer of them the identity is returned (nothing to compare with).
        gain_range: limits (a frame far off them is not an exposure change but a wrong render).
        dead_band: gains all within this of 1 are taken as 1. The fit is relative to the map, which earlier
            frames coloured with their own fitted gains, so its small errors would feed back and drift (a
            simulated robot camera with a fixed exposure crept to 0.93 in 45 frames); real auto-exposure
            changes are larger (7-Scenes: 0.75-1.43).
    """
    m = ((silhouette > min_silhouette) & (live_depth > 0))[..., None]  # [H, W, 1]
    n = m.sum()
    mc = (m & (live_rgb < SATURATED)).to(render_rgb.dtype)  # [H, W, 3]: a clipped pixel says nothing of the gain
    mu_r = (render_rgb * mc).sum((0, 1))  # [3] (sums: the pixel count cancels)
    mu_l = (live_rgb * mc).sum((0, 1))
    gain = (mu_l / mu_r.clamp_min(1e-3 * mc.sum((0, 1)).clamp_min(1.0))).clamp(*gain_range)
    out = torch.stack([gain, torch.zeros_like(gain)])
    keep = (n >= min_pixels) & ((gain - 1.0).abs().max() > dead_band)
    return torch.where(keep, out, identity(render_rgb.device).to(out.dtype))


def to_map(rgb: Tensor, exposure: Tensor) -> Tensor:
    """A frame's colour [H, W, 3] in the map's reference exposure (clamped to [0, 1])."""
    return ((rgb - exposure[1]) / exposure[0]).clamp(0.0, 1.0)


def to_frame(rgb: Tensor, exposure: Tensor) -> Tensor:
    """A render [H, W, 3] in the frame's exposure (clamped to [0, 1])."""
    return (rgb * exposure[0] + exposure[1]).clamp(0.0, 1.0)

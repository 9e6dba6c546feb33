"""Types and constants shared by the renderer back-ends (no back-end code here, so no import cycle).

:mod:`semantic_gs_slam.render` (pure-PyTorch tiles, the reference) and
:mod:`semantic_gs_slam.render.gsplat_backend` (CUDA fast path) both import this module and nothing of each
other's; :func:`semantic_gs_slam.render.select_backend` picks one from the config.

Compositing rules both back-ends follow (those of gsplat 1.5.3's CUDA kernel
``RasterizeToPixels3DGSFwd.cu``): front to back in depth order, ``alpha = opacity * exp(-d^2 / 2)``
with opacity = 0.99 * sigmoid(logit) (gsplat additionally caps alpha at 0.999, which never binds),
alphas below 1/255 skipped, and a pixel stops *before* the Gaussian that would take its
transmittance to <= 1e-4 (that Gaussian is not blended).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from torch import Tensor

from semantic_gs_slam.config import Intrinsics, RendererConfig

ALPHA_MIN = 1.0 / 255.0  # gsplat's ALPHA_THRESHOLD
OPACITY_CAP = 0.99  # opacity = OPACITY_CAP * sigmoid(logit) in both back-ends
STOP_TRANSMITTANCE = 1e-4  # gsplat's kernel: a pixel is done once T * (1 - alpha) <= 1e-4 (exclusive)
BLUR_PX2 = 0.3  # low-pass added to the 2-D covariance (gsplat eps2d, 3DGS)
FOV_MARGIN = 0.3  # projection Jacobian clamps x/z to the image plus 0.3 x tan(fov/2) on each side (gsplat)


@dataclass
class RenderOutput:
    """Rendered images (differentiable)."""

    rgb: Tensor  # [H, W, 3]
    depth: Tensor  # [H, W] sum of w_i z_i (not normalised by the silhouette, as SplaTAM renders it)
    silhouette: Tensor  # [H, W] accumulated opacity
    semantic: Tensor | None  # [H, W, S] or None
    n_visible: int = 0  # Gaussians in front of the camera that touch the image


@dataclass
class Gaussians:
    """Gaussian parameters as tensors (any of them may require grad)."""

    means: Tensor  # [N, 3] world
    quats: Tensor  # [N, 4] wxyz, unnormalised
    log_scales: Tensor  # [N, 1] isotropic or [N, 3]
    logit_opacities: Tensor  # [N, 1]
    rgb: Tensor  # [N, 3]
    semantic: Tensor | None = None  # [N, S]

    def check(self) -> None:
        """Raise ValueError on inconsistent shapes or tensors on different devices."""
        n = self.means.shape[0]
        want = {"means": (n, 3), "quats": (n, 4), "logit_opacities": (n, 1), "rgb": (n, 3)}
        for name, shape in want.items():
            if tuple(getattr(self, name).shape) != shape:
                raise ValueError(f"{name} must be {list(shape)}, got {list(getattr(self, name).shape)}")
        if self.log_scales.shape not in ((n, 1), (n, 3)):
            raise ValueError(f"log_scales must be [N, 1] or [N, 3], got {list(self.log_scales.shape)}")
        if self.semantic is not None and (self.semantic.ndim != 2 or self.semantic.shape[0] != n):
            raise ValueError(f"semantic must be [N, S], got {list(self.semantic.shape)}")
        devs = {t.device for t in (self.means, self.quats, self.log_scales, self.logit_opacities, self.rgb,
                                   self.semantic) if t is not None}
        if len(devs) > 1:
            raise ValueError(f"Gaussian tensors are on several devices: {sorted(str(d) for d in devs)}")


class RenderBackend(Protocol):
    """One renderer back-end: ``backend(g, w2c, k, cfg) -> RenderOutput``.

    Args:
        g: the Gaussians (all on one device).
        w2c: [4, 4] world-to-camera pose on the same device (may require grad).
        k: intrinsics (image size included).
        cfg: renderer settings.
    """

    def __call__(self, g: Gaussians, w2c: Tensor, k: Intrinsics, cfg: RendererConfig) -> RenderOutput: ...

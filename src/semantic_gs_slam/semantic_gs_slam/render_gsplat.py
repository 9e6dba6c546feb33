"""CUDA back-end through ``gsplat`` (optional GPU extra; not installed on CPU machines).

Same inputs and outputs as :func:`semantic_gs_slam.render.render`. Colour and semantic channels are
rendered as one feature stack with ``render_mode="RGB+D"`` (accumulated depth, not normalised, as
the torch back-end renders it); opacity is ``0.99 * sigmoid(logit)`` in both back-ends.
"""

from __future__ import annotations

import torch

from semantic_gs_slam.config import Intrinsics, RendererConfig
from semantic_gs_slam.errors import BackendUnavailableError
from semantic_gs_slam.render import OPACITY_CAP, Gaussians, RenderOutput


def gsplat_available() -> bool:
    """True when gsplat imports and a CUDA device exists."""
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return torch.cuda.is_available()


def render_gsplat(g: Gaussians, w2c: torch.Tensor, k: Intrinsics, cfg: RendererConfig) -> RenderOutput:
    """Render with ``gsplat.rasterization`` (CUDA tensors expected).

    Raises:
        BackendUnavailableError: gsplat is not installed or there is no CUDA device.
    """
    if not gsplat_available():
        raise BackendUnavailableError("renderer backend 'gsplat' needs the gsplat package and a CUDA GPU; "
                                      "use backend='torch' on this machine")
    from gsplat import rasterization

    ls = g.log_scales
    scales = torch.exp(ls if ls.shape[1] == 3 else ls.expand(-1, 3))
    feats = g.rgb if g.semantic is None else torch.cat([g.rgb, g.semantic], -1)
    kmat = torch.tensor(k.as_matrix(), dtype=g.means.dtype, device=g.means.device)
    img, alpha, _ = rasterization(
        g.means, g.quats / g.quats.norm(dim=-1, keepdim=True), scales,
        OPACITY_CAP * torch.sigmoid(g.logit_opacities[:, 0]), feats, w2c[None], kmat[None], k.width, k.height,
        near_plane=cfg.near, render_mode="RGB+D", packed=False, tile_size=16)
    img = img[0]
    c = feats.shape[1]
    sem = img[..., 3:c] if g.semantic is not None else None
    return RenderOutput(img[..., :3], img[..., c], alpha[0, ..., 0], sem, int(g.means.shape[0]))

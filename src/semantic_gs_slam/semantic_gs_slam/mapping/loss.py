"""The keyframe mapping loss and the refinement's pose prior (pure functions of tensors).

:func:`mapping_loss` is what :class:`~semantic_gs_slam.mapping.steps.MappingSteps` minimises over a window of
keyframes; :func:`pose_prior` is added per keyframe when the refinement also moves the keyframes' poses.
"""

from __future__ import annotations

import torch
from torch import Tensor

from semantic_gs_slam.config import MappingConfig
from semantic_gs_slam.eval.metrics import ssim
from semantic_gs_slam.render.types import RenderOutput


def _class_balance(sem: Tensor, power: float, cap: float = 20.0) -> Tensor:
    """Per-pixel weights [H, W] proportional to (class pixel frequency)^-power, mean 1, capped."""
    counts = torch.bincount(sem.reshape(-1).clamp_min(0)).double()
    w = (counts.clamp_min(1) / sem.numel()) ** (-power)
    pix = w[sem.clamp_min(0)]
    pix = (pix / pix.mean()).clamp(max=cap)
    return (pix / pix.mean()).float()


def mapping_loss(out: RenderOutput, rgb: Tensor, depth: Tensor, sem_img: Tensor | None, labelled: Tensor | None,
                 sem_w: Tensor | None, mc: MappingConfig) -> Tensor:
    """Keyframe mapping loss: depth L1 over valid depth + colour (L1 and SSIM) + class-balanced semantic L1.

    Fixed-shape (masks multiply; no boolean indexing), so it runs without host synchronisation.

    Args:
        out: the rendered view.
        rgb: [H, W, 3] keyframe colour. depth: [H, W] metres (0: missing).
        sem_img: [H, W, C] one-hot labels or None. labelled: [H, W] 1 where a label is known, or None.
        sem_w: [H, W] class-balance weights or None.
        mc: mapping settings (weights).

    Returns:
        Scalar loss.
    """
    valid = (depth > 0).to(depth.dtype)
    l_depth = ((out.depth - depth).abs() * valid).sum() / valid.sum().clamp_min(1.0)
    l1 = (out.rgb - rgb).abs().mean()
    fast = {"auto": None, "torch": False, "numba": True}[mc.ssim_backend]
    l_col = (1 - mc.w_ssim) * l1 + mc.w_ssim * (1 - ssim(out.rgb, rgb, fast=fast)) if mc.w_ssim > 0 else l1
    loss = mc.w_depth * l_depth + mc.w_colour * l_col
    if sem_img is not None and out.semantic is not None and mc.w_semantic > 0:
        err = (out.semantic - sem_img).abs().sum(-1) * labelled  # [H, W]; label 0 = unknown
        if sem_w is not None:
            err = err * sem_w
        loss = loss + mc.w_semantic * err.mean() / 2
    return loss


POSE_PRIOR_TRANS_M = 0.01  # scale of a keyframe's translation correction in pose_prior (1 cm)
POSE_PRIOR_ROT_QV = 0.004  # scale of its rotation correction, as a quaternion's vector part (~0.46 degrees)


def pose_prior(dq: Tensor, dt: Tensor, weight: float) -> Tensor:
    """``weight * (|dt|^2 / (1 cm)^2 + |dq|^2 / 0.004^2)``: the refinement's pull of a keyframe's pose correction
    (``dq`` [3], the vector part of a quaternion whose real part is 1; ``dt`` [3], metres) toward none. Scalar."""
    return weight * ((dt * dt).sum() / POSE_PRIOR_TRANS_M ** 2 + (dq * dq).sum() / POSE_PRIOR_ROT_QV ** 2)

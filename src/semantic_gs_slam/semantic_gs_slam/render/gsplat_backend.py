"""CUDA back-end through ``gsplat`` 1.5.3 (the fast path; :mod:`semantic_gs_slam.render` is the reference).

Same inputs and outputs as :func:`semantic_gs_slam.render.render_torch`, and the same image: colour
and semantic channels are rendered as one feature stack with ``render_mode="RGB+D"`` (depth
``sum w_i z_i``, not normalised, as the torch back-end renders it), opacity is
``0.99 * sigmoid(logit)``, ``eps2d=0.3`` in ``classic`` mode (no opacity compensation), the same near
plane, and the principal point shifted by +0.5 px because gsplat samples pixel (c, r) at
(c + 0.5, r + 0.5) while our pixel centres are at integer coordinates. gsplat's kernel rules (1/255
skip, transmittance stop) are the torch back-end's, see :mod:`semantic_gs_slam.render.types`.

This module imports gsplat only when it renders (gsplat compiles its CUDA code on first use), and
imports nothing of :mod:`semantic_gs_slam.render`.
"""

from __future__ import annotations

import torch

from semantic_gs_slam.config import Intrinsics, RendererConfig
from semantic_gs_slam.errors import BackendUnavailableError
from semantic_gs_slam.render.types import BLUR_PX2, OPACITY_CAP, Gaussians, RenderOutput

GSPLAT_TILE = 16  # gsplat's tile edge (pixels); only speed depends on it


def gsplat_available() -> bool:
    """True when gsplat imports and a CUDA device exists."""
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return torch.cuda.is_available()


_EXTENSION: dict[str, object] = {}  # the one attempt per process to load gsplat's CUDA code: {"ok": bool, "why": str}


def load_gsplat_extension() -> tuple[bool, str]:
    """Load gsplat's compiled CUDA code now, once per process; returns (loaded, why not).

    gsplat compiles its CUDA code with torch's JIT loader on first use: ~85 s after an install, and again
    whenever gsplat's build flags (``FAST_COMPILE``, ``NO_FAST_MATH``, ``TORCH_CUDA_ARCH_LIST``) differ from the
    last build's. The engine calls this when it chooses its renderer, so that time is spent at start, not at
    the first frame, and a build that cannot succeed (no ``nvcc``) is found before any frame arrives.
    """
    if not _EXTENSION:
        try:
            from gsplat.cuda._backend import _C
        except Exception as exc:  # noqa: BLE001  (a failed build raises ImportError, OSError or RuntimeError)
            _EXTENSION.update(ok=False, why=f"{type(exc).__name__}: {exc}".splitlines()[0][:300])
        else:
            _EXTENSION.update(ok=_C is not None, why="" if _C is not None else "gsplat found no CUDA toolkit (nvcc)")
    return bool(_EXTENSION["ok"]), str(_EXTENSION["why"])


def require_gsplat() -> None:
    """Raise :class:`BackendUnavailableError` unless gsplat, a CUDA device and gsplat's built CUDA code exist."""
    if not gsplat_available():
        raise BackendUnavailableError("renderer backend 'gsplat' needs the gsplat package and a CUDA GPU; "
                                      "use backend='torch' on this machine (or `make setup-gpu` on a CUDA one)")
    ok, why = load_gsplat_extension()
    if not ok:
        raise BackendUnavailableError(f"renderer backend 'gsplat': gsplat's CUDA code did not build or load ({why}); "
                                      "it needs nvcc (CUDA_HOME) matching torch's CUDA: `make setup-gpu` shows "
                                      "the build, or use backend='torch'")


def gsplat_intrinsics(k: Intrinsics, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """[3, 3] K in gsplat's pixel convention (pixel centres at +0.5): our K with cx, cy shifted by +0.5."""
    return torch.tensor([[k.fx, 0.0, k.cx + 0.5], [0.0, k.fy, k.cy + 0.5], [0.0, 0.0, 1.0]], dtype=dtype,
                        device=device)


def gsplat_inputs(g: Gaussians) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Unit quaternions [N, 4], scales [N, 3], opacities [N] and features [N, 3 + S] as gsplat takes them."""
    ls = g.log_scales
    scales = torch.exp(ls if ls.shape[1] == 3 else ls.expand(-1, 3))
    quats = g.quats / g.quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    opac = OPACITY_CAP * torch.sigmoid(g.logit_opacities[:, 0])
    feats = g.rgb if g.semantic is None else torch.cat([g.rgb, g.semantic], -1)
    return quats, scales, opac, feats


def render_gsplat(g: Gaussians, w2c: torch.Tensor, k: Intrinsics, cfg: RendererConfig) -> RenderOutput:
    """Render with ``gsplat.rasterization`` (CUDA tensors). Arguments as :func:`semantic_gs_slam.render.render`.

    Raises:
        BackendUnavailableError: gsplat is not installed or there is no CUDA device.
        ValueError: inconsistent shapes or devices.
    """
    require_gsplat()
    g.check()
    if tuple(w2c.shape) != (4, 4):
        raise ValueError(f"w2c must be [4, 4], got {list(w2c.shape)}")
    from gsplat import rasterization

    quats, scales, opac, feats = gsplat_inputs(g)
    kmat = gsplat_intrinsics(k, g.means.dtype, g.means.device)
    img, alpha, meta = rasterization(
        g.means, quats, scales, opac, feats, w2c.to(g.means.dtype)[None], kmat[None], k.width, k.height,
        near_plane=cfg.near, eps2d=BLUR_PX2, render_mode="RGB+D", packed=False, tile_size=GSPLAT_TILE,
        rasterize_mode="classic")
    img = img[0]
    c = feats.shape[1]
    sem = img[..., 3:c] if g.semantic is not None else None
    radii = meta["radii"]  # [1, N, 2] (int); 0: culled
    n_vis = int((radii > 0).any(-1).sum())
    return RenderOutput(img[..., :3], img[..., c], alpha[0, ..., 0], sem, n_vis)

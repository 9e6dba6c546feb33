"""Compiled CPU SSIM (numba) against the grouped-convolution reference: value, gradient, dispatch, errors."""

from __future__ import annotations

import pytest
import torch

from semantic_gs_slam.devices import numba_available
from semantic_gs_slam.eval.metrics import ssim, ssim_reference
from semantic_gs_slam.eval.metrics_numba import ssim_numba

pytestmark = pytest.mark.skipif(not numba_available(), reason="numba not installed (the reference is used)")


@pytest.mark.parametrize("shape", [(48, 64, 3), (13, 9, 3), (20, 30, 1)])  # smaller than the window too
@pytest.mark.parametrize("window", [(11, 1.5), (7, 1.0)])
def test_numba_ssim_and_its_gradient_match_the_reference(shape, window):
    gen = torch.Generator().manual_seed(sum(shape))
    b = torch.rand(shape, generator=gen)
    a = (b + 0.15 * torch.randn(shape, generator=gen)).clamp(0, 1).requires_grad_(True)
    ref = ssim_reference(a, b, *window)
    got = ssim(a, b, *window, fast=True)
    torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-6)
    g_ref, = torch.autograd.grad(ref * 2.5, a)
    g_got, = torch.autograd.grad(got * 2.5, a)
    assert float((g_got - g_ref).norm()) <= 1e-4 * float(g_ref.norm())
    assert 0.2 < float(ref.detach()) < 0.99 and float(g_ref.abs().max()) > 0


def test_numba_ssim_of_an_image_with_itself_is_one():
    a = torch.rand(30, 40, 3)
    assert abs(float(ssim(a, a, fast=True)) - 1.0) < 1e-5


def test_ssim_picks_the_kernel_only_where_it_applies(monkeypatch):
    import semantic_gs_slam.eval.metrics as metrics

    calls = []
    monkeypatch.setattr(metrics, "ssim_numba", lambda *a: calls.append(1) or ssim_numba(*a))
    a, b = torch.rand(16, 16, 3), torch.rand(16, 16, 3)
    ssim(a, b)
    assert calls == [1]  # float32 on the CPU: the kernel
    ssim(a.double(), b.double())
    ssim(a, b.clone().requires_grad_(True))  # a gradient for the target: only the reference has one
    ssim(a, b, fast=False)
    assert calls == [1]


def test_numba_ssim_refuses_what_it_cannot_do():
    with pytest.raises(ValueError, match="first image only"):
        ssim(torch.rand(8, 8, 3), torch.rand(8, 8, 3, requires_grad=True), fast=True)
    with pytest.raises(ValueError, match="odd"):
        ssim(torch.rand(12, 12, 3), torch.rand(12, 12, 3), size=6, fast=True)
    with pytest.raises(ValueError, match="float32 CPU"):
        ssim(torch.rand(8, 8, 3).double(), torch.rand(8, 8, 3).double(), fast=True)
    with pytest.raises(ValueError, match="one shape"):
        ssim(torch.rand(8, 8, 3), torch.rand(8, 9, 3), fast=True)


def test_mapping_loss_follows_the_ssim_backend_setting():
    from semantic_gs_slam.config import ConfigError, MappingConfig
    from semantic_gs_slam.mapping.loss import mapping_loss
    from semantic_gs_slam.render.types import RenderOutput

    gen = torch.Generator().manual_seed(3)
    out = RenderOutput(torch.rand(20, 24, 3, generator=gen), torch.rand(20, 24, generator=gen),
                       torch.ones(20, 24), None)
    rgb, depth = torch.rand(20, 24, 3, generator=gen), torch.rand(20, 24, generator=gen)
    losses = [float(mapping_loss(out, rgb, depth, None, None, None, MappingConfig(ssim_backend=b)))
              for b in ("torch", "numba", "auto")]
    assert abs(losses[0] - losses[1]) < 1e-6 and losses[1] == losses[2]
    with pytest.raises(ConfigError, match="ssim_backend"):
        MappingConfig(ssim_backend="fast").check()

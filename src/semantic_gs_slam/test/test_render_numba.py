"""Compiled CPU compositor (numba) against the pure-PyTorch reference: images, gradients, threads, errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from semantic_gs_slam.config import ConfigError, Intrinsics, RendererConfig
from semantic_gs_slam.devices import numba_available
from semantic_gs_slam.errors import BackendUnavailableError
from semantic_gs_slam.render import Gaussians, render_torch, select_backend
from semantic_gs_slam.render.numba_backend import render_numba

pytestmark = pytest.mark.skipif(not numba_available(), reason="numba not installed (the reference is used)")

F32 = torch.float32


def scene(n: int = 300, seed: int = 0, aniso: bool = False, opaque: bool = False, semantic: int = 3) -> Gaussians:
    """Random Gaussians in front of an identity camera, float32 like the engine's."""
    gen = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=gen) * torch.tensor([0.6, 0.45, 0.3]) + torch.tensor([0.0, 0.0, 2.5])
    scales = torch.log(torch.rand(n, 3 if aniso else 1, generator=gen) * 0.06 + 0.01)
    logits = torch.randn(n, 1, generator=gen) * 2 + (4.0 if opaque else 0.0)
    g = Gaussians(means, torch.randn(n, 4, generator=gen), scales, logits, torch.rand(n, 3, generator=gen),
                  torch.rand(n, semantic, generator=gen) if semantic else None)
    for t in (g.means, g.quats, g.log_scales, g.logit_opacities, g.rgb, g.semantic):
        if t is not None:
            t.requires_grad_(True)
    return g


def loss_of(out) -> torch.Tensor:
    """A scalar that weighs every output channel differently (so every gradient path is exercised)."""
    gen = torch.Generator().manual_seed(7)
    terms = [(out.rgb * torch.rand(out.rgb.shape, generator=gen)).sum(), (out.depth ** 2).sum() * 0.3,
             (out.silhouette * torch.rand(out.silhouette.shape, generator=gen)).sum()]
    if out.semantic is not None:
        terms.append((out.semantic * torch.rand(out.semantic.shape, generator=gen)).sum())
    return sum(terms)


def params(g: Gaussians) -> list[torch.Tensor]:
    return [t for t in (g.means, g.quats, g.log_scales, g.logit_opacities, g.rgb, g.semantic)
            if t is not None and t.requires_grad]


def compare(g: Gaussians, k: Intrinsics, cfg: RendererConfig, w2c: torch.Tensor | None = None) -> None:
    """Images, every Gaussian parameter's gradient and the pose's gradient (photometric tracking uses it)."""
    w2c = (torch.eye(4) if w2c is None else w2c).clone().requires_grad_(True)
    a, b = render_numba(g, w2c, k, cfg), render_torch(g, w2c, k, cfg)
    assert a.n_visible == b.n_visible
    for name in ("rgb", "depth", "silhouette", "semantic"):
        x, y = getattr(a, name), getattr(b, name)
        if y is None:
            assert x is None
            continue
        assert x.shape == y.shape and x.dtype == y.dtype
        torch.testing.assert_close(x, y, rtol=1e-4, atol=2e-5)
    ga = torch.autograd.grad(loss_of(a), params(g) + [w2c], allow_unused=True)
    gb = torch.autograd.grad(loss_of(b), params(g) + [w2c], allow_unused=True)
    assert float(gb[-1].abs().max()) > 0  # the pose's gradient is not trivially zero
    for x, y in zip(ga, gb, strict=True):
        if y is None:
            assert x is None or float(x.abs().max()) == 0
            continue
        # relative to the gradient's size (float32 sums in a different order)
        assert float((x - y).norm()) <= 1e-4 * float(y.norm()) + 1e-6, (float((x - y).norm()), float(y.norm()))


@pytest.mark.parametrize("aniso", [False, True])
@pytest.mark.parametrize("size", [(64, 48), (37, 29)])  # tiles that fit, and partial edge tiles
def test_numba_compositor_matches_the_reference(aniso, size):
    k = Intrinsics(size[0], size[1], 50.0, 50.0, size[0] / 2 - 0.5, size[1] / 2 - 0.5)
    compare(scene(aniso=aniso, seed=1 + aniso), k, RendererConfig(backend="numba"))


@pytest.mark.parametrize("tile", [4, 16])
def test_numba_compositor_matches_with_early_termination_and_other_tiles(tile):
    """Opaque, overlapping Gaussians: most pixels stop before their tile's last pair."""
    g = scene(n=500, seed=3, opaque=True, semantic=0)
    k = Intrinsics(48, 40, 60.0, 60.0, 23.5, 19.5)
    compare(g, k, RendererConfig(tile=tile, backend="numba"))
    with torch.no_grad():
        stop = render_numba(g, torch.eye(4), k, RendererConfig(tile=tile))
        no_stop = render_numba(g, torch.eye(4), k, RendererConfig(tile=tile, stop_transmittance=0.0))
        no_stop_ref = render_torch(g, torch.eye(4), k, RendererConfig(tile=tile, stop_transmittance=0.0))
    assert float((stop.rgb - no_stop.rgb).abs().max()) > 1e-4  # pixels did end early (the rule took effect)
    torch.testing.assert_close(no_stop.rgb, no_stop_ref.rgb, rtol=1e-4, atol=2e-5)


def test_numba_compositor_with_nothing_visible_renders_zeros_and_zero_gradients():
    g = scene(n=20, seed=4)
    w2c = torch.eye(4)
    w2c[2, 3] = -10.0  # everything behind the camera
    k = Intrinsics(32, 24, 30.0, 30.0, 15.5, 11.5)
    out = render_numba(g, w2c, k, RendererConfig())
    assert out.n_visible == 0 and float(out.silhouette.detach().abs().sum()) == 0 and out.rgb.shape == (24, 32, 3)
    grads = torch.autograd.grad(loss_of(out), [g.means, g.rgb], allow_unused=True)
    assert all(gr is None or float(gr.abs().sum()) == 0 for gr in grads)


def test_numba_result_does_not_depend_on_the_number_of_threads():
    g = scene(n=400, seed=5)
    k = Intrinsics(64, 48, 50.0, 50.0, 31.5, 23.5)
    before = torch.get_num_threads()
    results = []
    try:
        for n in (1, 2, 3):
            torch.set_num_threads(n)
            out = render_numba(g, torch.eye(4), k, RendererConfig())
            results.append((out.rgb.detach().clone(), torch.autograd.grad(loss_of(out), [g.means])[0]))
    finally:
        torch.set_num_threads(before)
    for rgb, gm in results[1:]:
        assert torch.equal(rgb, results[0][0]) and torch.equal(gm, results[0][1])


@pytest.mark.slow
def test_numba_renders_from_three_python_threads_at_once():
    """numba's ``workqueue`` threading layer (its fallback without OpenMP or TBB) aborts the process when two Python
    threads enter it at once; the module's lock serialises the calls. Run with that layer forced, in a subprocess (an
    abort there fails this test instead of ending the test run)."""
    import subprocess
    import sys

    code = (
        "import threading, torch\n"
        "import numba\n"
        "from semantic_gs_slam.config import Intrinsics, RendererConfig\n"
        "from semantic_gs_slam.render import Gaussians\n"
        "from semantic_gs_slam.render.numba_backend import render_numba\n"
        "torch.set_num_threads(2)\n"
        "gen = torch.Generator().manual_seed(6)\n"
        "n = 400\n"
        "g = Gaussians(torch.randn(n, 3, generator=gen) * 0.5 + torch.tensor([0, 0, 2.5]), torch.randn(n, 4),\n"
        "              torch.full((n, 1), -3.0), torch.randn(n, 1, generator=gen), torch.rand(n, 3, generator=gen))\n"
        "k = Intrinsics(96, 72, 70.0, 70.0, 47.5, 35.5)\n"
        "want = render_numba(g, torch.eye(4), k, RendererConfig()).rgb\n"
        "got = []\n"
        "def work():\n"
        "    for _ in range(20):\n"
        "        got.append(render_numba(g, torch.eye(4), k, RendererConfig()).rgb)\n"
        "ts = [threading.Thread(target=work) for _ in range(3)]\n"
        "[t.start() for t in ts]; [t.join() for t in ts]\n"
        "assert len(got) == 60 and all(torch.equal(x, want) for x in got)\n"
        "print(numba.threading_layer())\n")
    import os

    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                       env={**os.environ, "NUMBA_THREADING_LAYER": "workqueue"})
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip() == "workqueue"


def test_float64_gaussians_go_to_the_reference():
    g = scene(n=200, seed=10)
    g64 = Gaussians(*(t.detach().double() for t in (g.means, g.quats, g.log_scales, g.logit_opacities, g.rgb,
                                                     g.semantic)))
    k = Intrinsics(40, 30, 30.0, 30.0, 19.5, 14.5)
    a = render_numba(g64, torch.eye(4, dtype=torch.float64), k, RendererConfig())
    b = render_torch(g64, torch.eye(4, dtype=torch.float64), k, RendererConfig())
    assert a.rgb.dtype == torch.float64 and torch.equal(a.rgb, b.rgb) and torch.equal(a.depth, b.depth)


def test_auto_picks_numba_on_the_cpu_and_the_choice_is_a_setting():
    assert select_backend(RendererConfig(), "cpu") is render_numba
    assert select_backend(RendererConfig(backend="numba"), "cpu") is render_numba
    assert select_backend(RendererConfig(backend="torch"), "cpu") is render_torch
    RendererConfig(backend="numba").check()
    with pytest.raises(ConfigError, match="'numba'"):
        RendererConfig(backend="numbaa").check()


def test_numba_refuses_gaussians_off_the_cpu():
    g = scene(n=4, seed=8)
    g = Gaussians(*(t.detach().to("meta") for t in (g.means, g.quats, g.log_scales, g.logit_opacities, g.rgb)))
    with pytest.raises(BackendUnavailableError, match="runs on the CPU"):
        render_numba(g, torch.eye(4, device="meta"), Intrinsics(8, 8, 8.0, 8.0, 3.5, 3.5), RendererConfig())


def test_numba_missing_is_a_typed_error(monkeypatch):
    import semantic_gs_slam.devices as devices
    import semantic_gs_slam.render as render_mod

    monkeypatch.setattr(devices, "numba_available", lambda: False)
    monkeypatch.setattr(render_mod, "numba_available", lambda: False)
    with pytest.raises(BackendUnavailableError, match="numba"):
        select_backend(RendererConfig(backend="numba"), "cpu")
    assert select_backend(RendererConfig(), "cpu") is render_torch  # auto falls back to the reference


def test_compiled_binning_gives_the_reference_pairs_in_the_reference_order():
    from semantic_gs_slam.render.numba_backend import bin_pairs_numba
    from semantic_gs_slam.render.tiles import bin_pairs_torch, tile_pairs

    g = scene(n=500, seed=9, aniso=True)
    k = Intrinsics(61, 47, 50.0, 50.0, 30.0, 23.0)
    with torch.no_grad():
        a = tile_pairs(g, torch.eye(4), k, RendererConfig(), bin_pairs_torch)
        b = tile_pairs(g, torch.eye(4), k, RendererConfig(), bin_pairs_numba)
    assert a.pg.numel() > 2 * a.n_visible  # footprints that span several tiles
    for name in ("pg", "tstart", "tcount", "tiles_sorted"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert torch.equal(a.coef, b.coef)


@pytest.mark.slow
def test_cpu_kernels_bench_prints_every_row_with_agreeing_results(capsys, tmp_path):
    """``bench/cpu_kernels.py`` on every 8th Gaussian of the bundled map (5 141 of 41 128; the whole map made this
    test 52 s of CPU, nearly all in the reference renderer) at a small size: five rows, each with both timings, and
    the fast path's results close to the reference's."""
    import os
    import sys

    root = os.path.join(os.path.dirname(__file__), "..", "..", "..")
    bench = os.path.join(root, "bench")
    sys.path.insert(0, bench)
    try:
        import cpu_kernels
    finally:
        sys.path.remove(bench)
    with np.load(os.path.join(root, "data", "params.npz")) as z:
        n = len(z["means3D"])
        np.savez(tmp_path / "params.npz", **{k: z[k][::8] if z[k].ndim and len(z[k]) == n else z[k] for k in z.files})
    assert cpu_kernels.main(["--map", str(tmp_path / "params.npz"), "--size", "96x54", "--reps", "1",
                             "--threads", "1"]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| ") and "ms" not in line]
    assert len(rows) == 5, rows
    for line in rows:
        cells = [c.strip() for c in line.strip("|").split("|")]
        assert float(cells[1]) > 0 and float(cells[2]) > 0
        assert float(cells[4].split()[0]) < 1e-3, line  # results apart


@pytest.mark.slow
def test_compiled_kernels_come_from_numba_s_disk_cache_in_a_new_process():
    """The kernels are module-level functions, so a second process loads them from numba's cache instead of
    compiling them again (kernels defined inside a function were recompiled in every process: ~10 s a start)."""
    import subprocess
    import sys

    code = (
        "import torch\n"
        "from semantic_gs_slam.eval import numba_kernels as ek\n"
        "from semantic_gs_slam.render import numba_kernels as rk\n"
        "from semantic_gs_slam.tracking import numba_kernels as tk\n"
        "from semantic_gs_slam.config import Intrinsics, RendererConfig, TrackingConfig\n"
        "from semantic_gs_slam.eval.metrics import ssim\n"
        "from semantic_gs_slam.render import Gaussians\n"
        "from semantic_gs_slam.render.numba_backend import render_numba\n"
        "g = Gaussians(torch.randn(30, 3) * 0.3 + torch.tensor([0, 0, 2.0]), torch.randn(30, 4),\n"
        "              torch.full((30, 1), -3.0), torch.zeros(30, 1), torch.rand(30, 3))\n"
        "g.means.requires_grad_(True)\n"
        "k = Intrinsics(16, 12, 15.0, 15.0, 7.5, 5.5)\n"
        "render_numba(g, torch.eye(4), k, RendererConfig()).rgb.sum().backward()\n"
        "ssim(torch.rand(12, 12, 3, requires_grad=True), torch.rand(12, 12, 3)).backward()\n"
        "from semantic_gs_slam.tracking.icp_numba import normal_equations_numba\n"
        "e, f = torch.eye(4, dtype=torch.float64), torch.zeros(12 * 16, 3, dtype=torch.float64)\n"
        "normal_equations_numba(e, f[:4], f[:4, 0] > 0, None, f, f, f[:, 0] > 0, None, e, k, TrackingConfig(), False)\n"
        "fns = (rk.composite_forward, rk.composite_backward, rk.bin_pairs, ek.ssim_forward, ek.ssim_backward,\n"
        "       tk.icp_accumulate)\n"
        "print(sum(len(f.stats.cache_hits) for f in fns), sum(len(f.stats.cache_misses) for f in fns))\n")
    def run() -> tuple[int, int]:
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr
        hits, misses = (int(x) for x in r.stdout.split())
        return hits, misses

    hits, misses = run()
    if misses:  # a cold cache (a fresh checkout): this process compiled and wrote it; the next one must load it
        hits, misses = run()
    assert hits >= 6 and misses == 0, (hits, misses)


def test_compiled_paths_asked_for_off_the_cpu_are_refused_when_the_engine_starts(monkeypatch):
    """``numba`` for the renderer, ICP or SSIM on a CUDA engine: a typed error at start, not at the first frame
    (the device check is what is tested; the CUDA device itself is not needed for it)."""
    import semantic_gs_slam.slam as slam_mod
    from semantic_gs_slam.config import MappingConfig, SlamConfig, TrackingConfig
    from semantic_gs_slam.slam import SLAM

    with pytest.raises(BackendUnavailableError, match="renderer.backend 'numba' runs on the CPU"):
        select_backend(RendererConfig(backend="numba"), "cuda")
    k = Intrinsics(16, 12, 15.0, 15.0, 7.5, 5.5)
    monkeypatch.setattr(slam_mod, "resolve_device", lambda name: torch.device("cuda"))
    monkeypatch.setattr(slam_mod, "select_backend", lambda cfg, dev: render_torch)  # the renderer is not the point
    for cfg, what in ((SlamConfig(intrinsics=k, tracking=TrackingConfig(icp_backend="numba")), "icp_backend"),
                      (SlamConfig(intrinsics=k, mapping=MappingConfig(ssim_backend="numba")), "ssim_backend")):
        with pytest.raises(BackendUnavailableError, match=what):
            SLAM(cfg)

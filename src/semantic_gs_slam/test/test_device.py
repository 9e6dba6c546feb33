"""The engine on any torch device, checked on a CPU-only machine.

* :class:`~semantic_gs_slam.device_guard.DeviceGuard` over whole frames (keyframe, densify, prune,
  checkpoint, save, resume): no tensor factory without a device from engine code; host
  synchronisations counted and printed per frame.
* ``torch.set_default_device("meta")`` during a run on ``device="cpu"``: a tensor made without a
  device lands on ``meta`` and breaks the run at the first place that mixes it in.
* The fixed-shape pieces (projection, compositing forward/backward, losses, pose update) on the
  ``meta`` device with autograd, and forward under ``FakeTensorMode`` on a fake ``cuda`` device
  (a CPU tensor mixed in raises ``FakeTensorDeviceMismatchError``).
* Device / back-end selection and the back-end modules' imports (no cycle).
"""

from __future__ import annotations

import os
import subprocess
import sys
import types

import numpy as np
import pytest
import torch
from torch.overrides import TorchFunctionMode

import semantic_gs_slam.render.gsplat_backend as rgm
from semantic_gs_slam.config import Intrinsics, MappingConfig, RendererConfig, SlamConfig
from semantic_gs_slam.device_guard import PACKAGE_DIR, DeviceGuard
from semantic_gs_slam.devices import numba_available, resolve_device
from semantic_gs_slam.errors import BackendUnavailableError, ConfigError
from semantic_gs_slam.io.datasets import load_dataset
from semantic_gs_slam.mapping.loss import mapping_loss
from semantic_gs_slam.render import project_rows, render_torch, select_backend
from semantic_gs_slam.render.numba_backend import render_numba
from semantic_gs_slam.render.reference import _Composite
from semantic_gs_slam.render.types import RenderOutput
from semantic_gs_slam.slam import SLAM
from semantic_gs_slam.tracking.tracker import photometric_loss_of, w2c_from_quat_trans

K = Intrinsics(32, 24, 30.0, 30.0, 15.5, 11.5)


def _engine_config(ds, tmp_path, reference: bool = False) -> SlamConfig:
    """A short engine run's settings; ``reference``: the pure-PyTorch paths everywhere (what runs on a GPU), not the
    compiled CPU kernels that ``auto`` picks where numba is installed."""
    cfg = SlamConfig(intrinsics=ds.intrinsics, device="cpu", threads=1,
                     mapping=MappingConfig(first_frame_iters=30, iters=3, keyframe_every=2, prune_every=1),
                     checkpoint_every=3, checkpoint_dir=str(tmp_path / "ck"))
    if reference:
        cfg.renderer.backend, cfg.tracking.icp_backend, cfg.mapping.ssim_backend = "torch", "torch", "torch"
    return cfg


def test_guard_catches_a_planted_device_less_factory_and_counts_syncs():
    # code compiled as if it were an engine module: the guard must see it (else the engine test proves nothing)
    code = compile("a = torch.zeros(3)\nb = torch.ones(3, device='cpu')\nx = float(b.sum())\n"
                   "y = bool(b.any())\nz = b.tolist()\nw = b.sum().item()\nv = b.cpu().numpy()\n",
                   os.path.join(PACKAGE_DIR, "planted.py"), "exec")
    with DeviceGuard() as guard:
        exec(code, {"torch": torch})
        n = guard.end_frame()
        torch.zeros(3)  # test code, not the engine: not counted
    assert guard.violations == ["planted.py:1 torch.zeros"]
    assert n == 6 and guard.factory_calls == 2  # float, bool, tolist, item, cpu, numpy


@pytest.mark.parametrize("reference", [True, False])
def test_engine_frames_make_every_tensor_with_a_device_and_print_syncs(tiny_home, tmp_path, reference):
    """Both the reference paths and the compiled CPU kernels make no tensor without a device. The host
    synchronisations are bounded on the reference paths (those that run on a GPU); the CPU kernels hand arrays to
    numba, which the guard counts as host copies, free on a CPU."""
    ds = load_dataset(str(tiny_home))
    frames = [ds[i] for i in range(5)]
    with DeviceGuard() as guard:
        eng = SLAM(_engine_config(ds, tmp_path, reference), ds.classes)
        for f in frames[:4]:  # keyframes 0 and 2 (densify, map, prune), densify-only 1 and 3, checkpoint after 3
            eng.add_frame(f.rgb, f.depth, f.semantics, f.timestamp, f.gt_c2w)
            guard.end_frame()
        eng.save(str(tmp_path / "map"))
        eng = SLAM.resume(str(tmp_path / "ck"))
        eng.add_frame(frames[3].rgb, frames[3].depth, frames[3].semantics, frames[3].timestamp, frames[3].gt_c2w)
        guard.end_frame()
    print(f"host syncs per frame: {guard.syncs_per_frame}; data-dependent ops per frame: {guard.implicit_per_frame}")
    print("most frequent sync sites:", guard.sync_sites.most_common(6))
    assert guard.violations == []
    assert guard.factory_calls > 50  # the guard did see the engine make tensors
    assert not any(lg.tracking_failed for lg in eng.logs)
    assert all(0 < n < (400 if reference else 1000) for n in guard.syncs_per_frame)


def test_engine_runs_with_default_device_meta(tiny_home, tmp_path):
    ds = load_dataset(str(tiny_home))
    frames = [ds[i] for i in range(3)]
    torch.set_default_device("meta")
    try:
        eng = SLAM(_engine_config(ds, tmp_path), ds.classes)
        for f in frames:
            eng.add_frame(f.rgb, f.depth, f.semantics, f.timestamp, f.gt_c2w)
        eng.checkpoint(str(tmp_path / "ck2"))
        eng = SLAM.resume(str(tmp_path / "ck2"))
        eng.save(str(tmp_path / "map2"))
    finally:
        torch.set_default_device(None)
    assert eng.map.params["means3D"].device.type == "cpu" and len(eng.map) > 100
    assert os.path.isfile(tmp_path / "map2" / "params.npz")


def _fixed_shape_pieces(dev: torch.device, grad: bool) -> dict[str, torch.Tensor]:
    """Projection, compositing, mapping and photometric losses, pose update on ``dev``; every output."""
    n, h, w = 40, K.height, K.width
    q = torch.randn(4, device=dev).requires_grad_(grad)
    t = torch.randn(3, device=dev).requires_grad_(grad)
    w2c = w2c_from_quat_trans(q, t)
    means = torch.randn(n, 3, device=dev)
    pc = means @ w2c[:3, :3].T + w2c[:3, 3]
    pr = project_rows(pc, torch.randn(n, 3, device=dev), torch.randn(n, 4, device=dev), torch.randn(n, 1, device=dev),
                      w2c, K)
    coef = torch.randn(3, 7, 6, device=dev).requires_grad_(grad)
    feats = torch.randn(3, 7, 5, device=dev).requires_grad_(grad)
    mono = torch.randn(6, 64, device=dev)
    if grad:
        comp = _Composite.apply(coef, feats, mono, 128, 1e-4)
    else:  # forward only: call the function directly with a stand-in context
        ctx = types.SimpleNamespace(save_for_backward=lambda *a: setattr(ctx, "saved_tensors", a))
        comp = _Composite.forward(ctx, coef, feats, mono, 128, 1e-4)
        comp_b = _Composite.backward(ctx, torch.randn_like(comp))[0]
    out = RenderOutput(torch.rand(h, w, 3, device=dev).requires_grad_(grad), torch.rand(h, w, device=dev),
                       torch.rand(h, w, device=dev), torch.rand(h, w, 4, device=dev))
    lm = mapping_loss(out, torch.rand(h, w, 3, device=dev), torch.rand(h, w, device=dev),
                      torch.rand(h, w, 4, device=dev), torch.rand(h, w, device=dev), torch.rand(h, w, device=dev),
                      MappingConfig())
    lp = photometric_loss_of(out, torch.rand(h, w, 3, device=dev), torch.rand(h, w, device=dev), 0.5)
    res = {"w2c": w2c, "uv": pr["uv"], "conic": pr["conic"], "composite": comp, "mapping": lm, "photometric": lp}
    if grad:
        (pr["uv"].sum() + pr["conic"].sum() + comp.sum() + lm + lp).backward()
        opt = torch.optim.Adam([q, t, coef, feats], lr=1e-3)
        opt.step()
        res.update(q=q, q_grad=q.grad, coef_grad=coef.grad, rgb_grad=out.rgb.grad)
    else:
        res["composite_backward"] = comp_b
    return res


def test_fixed_shape_pieces_forward_and_backward_stay_on_the_device():
    meta = torch.device("meta")
    res = _fixed_shape_pieces(meta, grad=True)
    assert {name: v.device.type for name, v in res.items()} == {name: "meta" for name in res}
    with pytest.raises((RuntimeError, NotImplementedError)):  # negative control: CPU mixed into meta
        res["uv"] + torch.zeros_like(res["uv"], device="cpu")


class _IndexingAsOps(TorchFunctionMode):
    """On a CPU-only torch, Python indexing of a fake CUDA tensor needs CUDA's device guard; route basic
    indexing through narrow / select / unsqueeze (the same view semantics) so FakeTensorMode can run."""

    def __torch_function__(self, func, types_, args=(), kwargs=None):  # noqa: D105
        if func is torch.Tensor.__getitem__ and args[0].device.type == "cuda":
            return _basic_index(*args)
        return func(*args, **(kwargs or {}))


def _basic_index(x: torch.Tensor, idx) -> torch.Tensor:
    idx = idx if isinstance(idx, tuple) else (idx,)
    consuming = sum(1 for i in idx if i is not None and i is not Ellipsis)
    d = 0
    for i in idx:
        if i is None:
            x = x.unsqueeze(d)
            d += 1
        elif i is Ellipsis:
            d += x.ndim - d - consuming
        elif isinstance(i, int):
            x = x.select(d, i)
            consuming -= 1
        elif isinstance(i, slice) and i.step in (None, 1):
            start, stop, _ = i.indices(x.shape[d])
            x = x.narrow(d, start, max(stop - start, 0))
            d += 1
            consuming -= 1
        else:
            raise NotImplementedError(f"index {i!r} in the fake-CUDA test")
    return x


def test_fixed_shape_pieces_forward_under_fake_cuda():
    if torch.cuda.is_available():
        # measured on an H200 (torch 2.11): real CUDA tensors cached by earlier tests leak into the fake mode
        # ("Please convert all Tensors to FakeTensors first"); there the real-GPU tests cover this
        pytest.skip("stands in for a GPU on machines without one")
    from torch._subclasses import fake_tensor
    from torch._subclasses.fake_tensor import FakeTensorMode

    # torch 2.13 has a dedicated error; 2.11 (the GPU machine's) raises a plain RuntimeError about the devices
    mismatch = getattr(fake_tensor, "FakeTensorDeviceMismatchError", RuntimeError)

    with FakeTensorMode(), _IndexingAsOps():
        cuda = torch.device("cuda")
        res = _fixed_shape_pieces(cuda, grad=False)
        assert {name: v.device.type for name, v in res.items()} == {name: "cuda" for name in res}
        with pytest.raises(mismatch, match="(?i)device"):  # negative control: a CPU tensor mixed in
            res["uv"] + torch.zeros(res["uv"].shape)


def test_device_selection_and_backend_choice():
    if torch.cuda.is_available():
        pytest.skip("this test describes a machine without CUDA")
    assert resolve_device("auto") == torch.device("cpu")
    with pytest.raises(ConfigError, match="no CUDA device"):
        resolve_device("cuda")
    with pytest.raises(ConfigError, match="device must be"):
        SlamConfig(intrinsics=K, device="gpu").check()
    with pytest.raises(ConfigError, match="no CUDA device"):
        SLAM(SlamConfig(intrinsics=K, device="cuda"))
    # auto on the CPU: the compiled compositor where numba is installed, else the torch tiles
    assert select_backend(RendererConfig(), "cpu") is (render_numba if numba_available() else render_torch)
    assert select_backend(RendererConfig(backend="torch"), "cpu") is render_torch
    with pytest.raises(BackendUnavailableError):
        select_backend(RendererConfig(backend="gsplat"), "cpu")
    assert SLAM(SlamConfig(intrinsics=K)).device == torch.device("cpu")


MODULES = ["render.types", "render.tiles", "render.gsplat_backend", "render.numba_backend", "render.reference",
           "render", "tracking.icp_numba", "eval.metrics_numba"]


# One process imports the third-party libraries (torch, numpy, numba: seconds), then forks a fresh child per module
# that imports only that module of this package: each child starts with none of semantic_gs_slam loaded, as a new
# interpreter would, without paying for torch's import eight times. A child's traceback is its result.
_IMPORT_EACH_ALONE = r"""
import os, sys, traceback
import numpy, torch
try:
    import numba
except ImportError:
    pass
assert not [m for m in sys.modules if m.split(".")[0] == "semantic_gs_slam"], "the package was imported first"
for name in sys.argv[1:]:
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(r)
        os.dup2(w, 1)
        os.dup2(w, 2)
        try:
            __import__("semantic_gs_slam." + name)
        except BaseException:
            traceback.print_exc()
            sys.stderr.flush()
            os._exit(1)
        os._exit(0)
    os.close(w)
    with os.fdopen(r, "rb") as f:
        out = f.read().decode("utf-8", "replace")
    code = os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])
    print(repr((name, code, out)), flush=True)
"""


@pytest.fixture(scope="module")
def imports_alone() -> dict[str, tuple[int, str]]:
    r = subprocess.run([sys.executable, "-c", _IMPORT_EACH_ALONE, *MODULES], capture_output=True, text=True,
                       timeout=240)
    assert r.returncode == 0, r.stdout + r.stderr
    import ast

    return {name: (code, out) for name, code, out in map(ast.literal_eval, r.stdout.splitlines())}


@pytest.mark.parametrize("name", MODULES)
def test_each_module_imports_alone(name, imports_alone):
    code, out = imports_alone[name]
    assert code == 0, out


def test_map_arrays_round_trip_keeps_the_device(tmp_path):
    from semantic_gs_slam.mapping.gaussian_map import GaussianMap

    m = GaussianMap("cpu")
    m.add(torch.rand(5, 3), torch.rand(5, 3), torch.tensor([0, 1, 1, 2, 0]), torch.full((5,), 0.01), 0)
    back = GaussianMap.from_arrays(m.to_arrays(), torch.device("cpu"))
    assert back.params["means3D"].device == back.semantic_ids.device == back.normals.device == torch.device("cpu")
    np.testing.assert_allclose(back.params["means3D"].detach().numpy(), m.params["means3D"].detach().numpy())


@pytest.fixture
def gsplat_outcome(monkeypatch):
    """A machine with a CUDA device and gsplat installed, where gsplat's JIT build gives ``outcome``.

    Only our choice of back-end is under test here: torch's CUDA check and gsplat's extension module are
    stand-ins (the real build runs on the GPU machine, ``make bench-gpu``); nothing is compiled or rendered.
    """
    if torch.cuda.is_available():
        pytest.skip("this test describes a machine without a working gsplat build; a GPU machine has the real one")
    pytest.importorskip("gsplat")

    def setup(outcome):
        monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
        monkeypatch.setattr(rgm, "_EXTENSION", {})
        mod = types.ModuleType("gsplat.cuda._backend")
        if isinstance(outcome, Exception):
            def fail(name):  # the module's import raises, as torch's JIT loader does when a build fails
                raise outcome
            mod.__getattr__ = fail
        else:
            mod._C = outcome
        monkeypatch.setitem(sys.modules, "gsplat.cuda._backend", mod)
        return rgm

    return setup


def test_gsplat_without_its_cuda_code_is_refused_at_start(gsplat_outcome):
    rg = gsplat_outcome(None)  # gsplat found no CUDA toolkit: its extension is None
    with pytest.raises(BackendUnavailableError, match="did not build or load.*no CUDA toolkit"):
        select_backend(RendererConfig(backend="gsplat"), "cuda")
    with pytest.warns(RuntimeWarning, match="PyTorch tiles instead"):
        assert select_backend(RendererConfig(), "cuda") is render_torch
    assert rg.load_gsplat_extension() == (False, "gsplat found no CUDA toolkit (nvcc)")


def test_gsplat_build_failure_is_one_clear_error(gsplat_outcome):
    rg = gsplat_outcome(OSError("CUDA_HOME environment variable is not set.\nmore lines"))
    first_line_only = r"\(OSError: CUDA_HOME environment variable is not set\.\); it needs"
    with pytest.raises(BackendUnavailableError, match=first_line_only):
        select_backend(RendererConfig(backend="gsplat"), "cuda")
    with pytest.raises(BackendUnavailableError, match="CUDA_HOME"):  # one attempt per process: same answer
        rg.require_gsplat()


def test_gsplat_loaded_at_start_is_chosen(gsplat_outcome):
    gsplat_outcome(object())  # a loaded extension
    assert select_backend(RendererConfig(), "cuda") is rgm.render_gsplat
    assert select_backend(RendererConfig(backend="gsplat"), "cuda") is rgm.render_gsplat

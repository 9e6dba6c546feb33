#!/usr/bin/env python3
"""The compiled CPU kernels (numba) against their pure-PyTorch references, same inputs, same run.

Usage (from the repository root, after ``source scripts/env.sh``)::

    python bench/cpu_kernels.py                      # the bundled map (data/params.npz), 2 threads
    python bench/cpu_kernels.py --map /tmp/run/params.npz --size 320x240 --threads 2
    python bench/cpu_kernels.py --write-figures      # also into docs/figures.md (block cpu_kernels_bundled_map)

For a map (any ``params.npz`` the engine wrote) seen from one of its own camera poses, each row times the
reference and the fast path alternately (``--reps`` each, median) and prints both, the ratio and how far the
results are apart:

* render, forward only (colour, depth, silhouette and the map's class columns, no gradient);
* render, forward and backward (every Gaussian parameter's gradient);
* one keyframe-mapping iteration as the engine runs it (render, mapping loss with SSIM, backward, Adam step);
* SSIM, forward and backward, at the image size;
* ICP of a live depth rendered 1 cm / 0.6 deg away against the model rendered at the pose (2 levels, a fixed
  number of steps so both paths do the same work).

Prints figures only (no targets here): the end-to-end effect is ``bench/slam_real.py``'s and
``bench/slam_synthetic.py``'s FPS.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time

import figures
import numpy as np
import torch

from semantic_gs_slam.config import Intrinsics, MappingConfig, RendererConfig, TrackingConfig
from semantic_gs_slam.devices import numba_available
from semantic_gs_slam.eval.metrics import ssim
from semantic_gs_slam.geometry import se3_exp
from semantic_gs_slam.mapping.gaussian_map import GaussianMap, load_params, trajectory_from_params
from semantic_gs_slam.mapping.loss import mapping_loss
from semantic_gs_slam.render import Gaussians, select_backend
from semantic_gs_slam.tracking.tracker import icp

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _ms(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return 1000 * (time.perf_counter() - t0)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--map", default=os.path.join(ROOT, "data", "params.npz"), help="a params.npz the engine wrote")
    ap.add_argument("--size", default="", help="WIDTHxHEIGHT (default: the map's own camera)")
    ap.add_argument("--frame", type=int, default=-1, help="camera pose of the map to look from (default: middle)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reps", type=int, default=7)
    figures.add_argument(ap)
    a = ap.parse_args(argv)
    provenance = figures.Provenance.start() if a.write_figures else None
    if not numba_available():
        print("numba is not installed: there is no fast path to compare (pip install -r requirements/python.in)",
              file=sys.stderr)
        return 2
    torch.set_num_threads(a.threads)
    arrays = load_params(a.map)
    gmap = GaussianMap.from_arrays(arrays)
    poses = trajectory_from_params(arrays)
    c2w = poses[len(poses) // 2 if a.frame < 0 else a.frame]
    km = np.asarray(arrays["intrinsics"], np.float64)
    w0, h0 = int(arrays["org_width"]), int(arrays["org_height"])
    w, h = (int(x) for x in a.size.lower().split("x")) if a.size else (w0, h0)
    k = Intrinsics(w, h, km[0, 0] * w / w0, km[1, 1] * h / h0, (km[0, 2] + 0.5) * w / w0 - 0.5,
                   (km[1, 2] + 0.5) * h / h0 - 0.5)
    w2c = torch.as_tensor(np.linalg.inv(c2w), dtype=torch.float32)
    backends = {"reference": select_backend(RendererConfig(backend="torch")),
                "numba": select_backend(RendererConfig(backend="numba"))}
    cfg = RendererConfig()
    rows = []

    def detached(shrink: float = 1.0, semantic: bool = True) -> Gaussians:
        g = gmap.gaussians()
        return Gaussians(g.means.detach(), g.quats.detach(), g.log_scales.detach() + math.log(shrink),
                         g.logit_opacities.detach(), g.rgb.detach(), g.semantic.detach() if semantic and
                         g.semantic is not None else None)

    def row(name: str, ref, fast, diff: float, unit: str) -> None:
        ref(), fast()  # warm-up (the first numba call loads or compiles its kernels)
        t_ref, t_fast = [], []
        for _ in range(a.reps):  # alternating, so both see the same machine load
            t_ref.append(_ms(ref))
            t_fast.append(_ms(fast))
        r, f = statistics.median(t_ref), statistics.median(t_fast)
        rows.append((name, r, f, diff, unit))

    # render, forward
    with torch.no_grad():
        outs = {n: b(detached(), w2c, k, cfg) for n, b in backends.items()}
    d = float((outs["reference"].rgb - outs["numba"].rgb).abs().max())
    row("render, forward", lambda: backends["reference"](detached(), w2c, k, cfg),
        lambda: backends["numba"](detached(), w2c, k, cfg), d, "colour, max abs")

    # render, forward + backward
    def fwd_bwd(name: str):
        def run():
            for v in gmap.params.values():
                v.grad = None
            out = backends[name](gmap.gaussians(), w2c, k, cfg)
            loss = out.rgb.sum() + out.depth.sum() + out.silhouette.sum()
            if out.semantic is not None:
                loss = loss + out.semantic.sum()
            loss.backward()
            return gmap.params["means3D"].grad.clone()
        return run
    g_ref, g_fast = fwd_bwd("reference")(), fwd_bwd("numba")()
    row("render, forward + backward", fwd_bwd("reference"), fwd_bwd("numba"),
        float((g_ref - g_fast).norm() / g_ref.norm()), "means gradient, relative")

    # one keyframe-mapping iteration (target: the map seen 1 cm away, so the loss is not zero)
    c2w_t = c2w @ se3_exp(torch.tensor([0.004, -0.006, 0.003, 0.01, 0.0, 0.0], dtype=torch.float64)).numpy()
    with torch.no_grad():
        tgt = backends["reference"](detached(), torch.as_tensor(np.linalg.inv(c2w_t), dtype=torch.float32), k, cfg)
    opt = torch.optim.Adam([{"params": [v], "lr": 0.0} for v in gmap.params.values()])  # lr 0: the map stays put

    def mapping_iteration(name: str, ssim_backend: str):
        mc = MappingConfig(ssim_backend=ssim_backend)

        def run():
            out = backends[name](gmap.gaussians(), w2c, k, cfg)
            loss = mapping_loss(out, tgt.rgb, tgt.depth, None, None, None, mc)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            return float(loss.detach())
        return run
    d = abs(mapping_iteration("reference", "torch")() - mapping_iteration("numba", "numba")())
    row("keyframe-mapping iteration", mapping_iteration("reference", "torch"), mapping_iteration("numba", "numba"), d,
        "loss, abs")

    # SSIM
    x = tgt.rgb.detach().clone().requires_grad_(True)
    y = outs["reference"].rgb.detach()

    def ssim_run(fast: bool):
        def run():
            s = ssim(x, y, fast=fast)
            s.backward()
            return float(s.detach())
        return run
    row("SSIM, forward + backward", ssim_run(False), ssim_run(True), abs(ssim_run(False)() - ssim_run(True)()),
        "value, abs")

    # ICP
    with torch.no_grad():
        model = backends["numba"](detached(0.35, False), w2c, k, cfg)
        live = backends["numba"](detached(), torch.as_tensor(np.linalg.inv(c2w_t), dtype=torch.float32), k, cfg)
    valid = model.silhouette > 0.5
    md = torch.where(valid, model.depth / model.silhouette.clamp_min(1e-6), torch.zeros_like(model.depth))
    ld = torch.where(live.silhouette > 0.5, live.depth / live.silhouette.clamp_min(1e-6), torch.zeros_like(live.depth))
    lrgb = live.rgb / live.silhouette.clamp_min(1e-6)[..., None]

    def icp_run(backend: str):
        tc = TrackingConfig(icp_backend=backend, icp_iters=12, icp_min_step=0.0)
        return lambda: icp(md, valid, torch.as_tensor(c2w), ld, k, tc, model.rgb, lrgb)
    p_ref, p_fast = icp_run("torch")().c2w, icp_run("numba")().c2w
    row("ICP, 2 levels x 12 steps", icp_run("torch"), icp_run("numba"), float((p_ref - p_fast).abs().max()),
        "pose, max abs")

    sem = gmap.gaussians().semantic
    lines = [f"map {a.map}: {len(gmap)} Gaussians, {0 if sem is None else sem.shape[1]} class columns; {w}x{h}; "
             f"{a.threads} threads; median of {a.reps}, reference and numba alternating",
             "| kernel | reference (PyTorch) ms | numba ms | ratio numba / reference | results apart |",
             "|---|---|---|---|---|"]
    lines += [f"| {name} | {r:.1f} | {f:.1f} | {f / r:.2f} | {d:.2e} ({unit}) |" for name, r, f, d, unit in rows]
    print("\n".join(lines))
    if provenance is not None:
        bundled = os.path.realpath(a.map) == os.path.realpath(os.path.join(ROOT, "data", "params.npz"))
        heading = (f"{os.path.relpath(a.map, ROOT) if bundled else 'map ' + os.path.basename(os.path.dirname(a.map))}: "
                   + lines[0].split(": ", 1)[1])
        figures.write_block("cpu_kernels_bundled_map" if bundled else "cpu_kernels_other_map",
                            heading + ":\n\n" + "\n".join(lines[1:]), provenance)
    return 0


if __name__ == "__main__":
    sys.exit(main())

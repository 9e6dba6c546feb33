"""Evaluation of a SLAM run: ATE RMSE (aligned), PSNR / SSIM / depth L1 of renders at the input views,
semantic mIoU, FPS and Gaussian count, printed as a table."""

from __future__ import annotations

import numpy as np
import torch

from semantic_gs_slam.eval.metrics import (
    ate_rmse,
    class_iou,
    confusion,
    depth_l1,
    miou,
    psnr,
    psnr_depth_masked,
    psnr_split,
    rpe_rmse,
    ssim,
)
from semantic_gs_slam.io.datasets import Dataset
from semantic_gs_slam.io.exposure import to_frame


def _nanmean(xs: list[float]) -> float:
    """Mean of the non-NaN values (NaN when there are none, without numpy's warning)."""
    vals = [x for x in xs if not np.isnan(x)]
    return float(np.mean(vals)) if vals else float("nan")


def evaluate(eng, ds: Dataset, frame_idx: list[int], every: int = 1) -> dict:
    """Metrics of ``eng`` (a :class:`~semantic_gs_slam.slam.SLAM` after the run) against ``ds``.

    Args:
        eng: the engine.
        ds: the dataset it was fed.
        frame_idx: dataset index of each engine frame.
        every: render-evaluate every k-th frame.

    Returns:
        dict with ate_rmse_cm, rpe_cm (:func:`~semantic_gs_slam.eval.metrics.rpe_rmse` over one frame step), psnr (all
        pixels), psnr_masked (SplaTAM's protocol:
        :func:`~semantic_gs_slam.eval.metrics.psnr_depth_masked`), psnr_with_depth / psnr_without_depth (the frames'
        mean :func:`~semantic_gs_slam.eval.metrics.psnr_split`; NaN without such pixels), ssim, depth_l1_cm, miou,
        class_iou (name -> IoU),
        gaussians, frames.
    """
    eng.drain(600.0)  # a mapping thread (SlamConfig.threaded) finishes the map first
    res = {"frames": len(eng.poses), "gaussians": len(eng.map)}
    gts = [ds[i].gt_c2w for i in frame_idx]
    if all(g is not None for g in gts):
        res["ate_rmse_cm"] = 100 * ate_rmse(eng.poses, gts)
        res["rpe_cm"] = 100 * rpe_rmse(eng.poses, gts, 1)
    ps, pm, ss, dl, pw, po = [], [], [], [], [], []
    conf = np.zeros((256, 256), np.int64)
    have_sem = False
    for n in range(0, len(frame_idx), every):
        f = ds[frame_idx[n]]
        out = eng.render_view(eng.poses[n])
        rgb = torch.as_tensor(f.rgb, device=eng.device)
        img = out.rgb.clamp(0, 1)
        exp = eng.exposure_of(n)
        if exp is not None:  # the map keeps the first frame's exposure: render in this frame's (exposure.py)
            img = to_frame(img, exp)
        depth = torch.as_tensor(f.depth, device=eng.device)
        ps.append(psnr(img, rgb))
        pm.append(psnr_depth_masked(img, rgb, depth))
        with_d, without_d = psnr_split(img, rgb, depth)
        pw.append(with_d)
        po.append(without_d)
        ss.append(float(ssim(img, rgb)))
        dl.append(depth_l1(out.depth, depth))
        if f.semantics is not None and out.semantic is not None:
            have_sem = True
            sem = out.semantic / out.silhouette.clamp_min(1e-6)[..., None]  # class scores, not scores x coverage
            pred = eng.map.labels_from_features(sem).cpu().numpy()
            conf += confusion(pred.clip(0, 255), f.semantics.clip(0, 255), 256)
    res.update(psnr=float(np.mean(ps)), psnr_masked=float(np.mean(pm)), ssim=float(np.mean(ss)),
               psnr_with_depth=_nanmean(pw), psnr_without_depth=_nanmean(po),
               depth_l1_cm=100 * float(np.nanmean(dl)))
    if have_sem:
        res["miou"] = miou(conf)
        res["class_iou"] = {eng.classes.get(c, str(c)): v for c, v in class_iou(conf).items()}
    return res


def format_table(res: dict) -> str:
    """Two-column text table of :func:`evaluate` results."""
    rows = [("frames", "frames", "{:d}"), ("ate_rmse_cm", "ATE RMSE (cm, aligned)", "{:.2f}"),
            ("rpe_cm", "RPE RMSE (cm, one frame step)", "{:.2f}"),
            ("psnr", "PSNR (dB)", "{:.2f}"),
            ("psnr_masked", "PSNR (dB), SplaTAM's protocol (pixels without depth zeroed)", "{:.2f}"),
            ("psnr_with_depth", "PSNR (dB), pixels with depth", "{:.2f}"),
            ("psnr_without_depth", "PSNR (dB), pixels without depth", "{:.2f}"),
            ("ssim", "SSIM", "{:.3f}"), ("depth_l1_cm", "depth L1 (cm)", "{:.2f}"),
            ("miou", "semantic mIoU", "{:.3f}"), ("fps", "FPS", "{:.2f}"), ("gaussians", "Gaussians", "{:d}")]
    lines = ["| metric | value |", "|---|---|"]
    for key, name, fmt in rows:
        if key in res and not (isinstance(res[key], float) and np.isnan(res[key])):
            lines.append(f"| {name} | {fmt.format(res[key])} |")
    if "class_iou" in res:
        lines.append("per-class IoU: " + ", ".join(f"{k} {v:.2f}" for k, v in res["class_iou"].items()))
    return "\n".join(lines)

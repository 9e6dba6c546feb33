"""The Gaussian map: parameters, densification, pruning, and the SplaTAM / SGS-SLAM file formats.

Parameters (torch leaf tensors in :attr:`GaussianMap.params`): ``means3D`` [N, 3], ``rgb_colors``
[N, 3], ``unnorm_rotations`` [N, 4] (wxyz), ``logit_opacities`` [N, 1], ``log_scales`` [N, 1]
(isotropic), ``semantic_features`` [N, C] (one column per class in :attr:`GaussianMap.class_slots`,
seeded one-hot, optimised through rendering; a Gaussian's class is its largest column).
Non-optimised: ``semantic_ids`` [N] (seed label), ``votes`` [N, C] (label votes over views, one
column per class slot: :meth:`GaussianMap.vote`), ``timestep`` [N] (frame that created the Gaussian)
and ``normals`` [N, 3] (world-frame surface normal measured at seeding, zero when unknown; used by
tracking to render unbiased depth, see :func:`semantic_gs_slam.tracking.tracker.plane_depth_features`).

Why class columns and not SGS-SLAM's 3-channel semantic colour: a rendered pixel is a blend of several
Gaussians, and a blend of two palette colours is often nearest a *third* class's colour (the palette
has 64 levels per channel), which turned object edges into spurious small-object labels (cup IoU
0.13). With one column per class a blend's largest column is always one of the blended classes.
Files still carry ``semantic_colors`` [N, 3] (the palette colour of each Gaussian's class) for
SplaTAM-family tools, plus ``semantic_features`` / ``semantic_feature_ids`` for our own reload.
"""

from __future__ import annotations

import json
import os
import zipfile

import numpy as np
import torch
from torch import Tensor

from semantic_gs_slam.config import Intrinsics
from semantic_gs_slam.errors import MapFormatError
from semantic_gs_slam.geometry import backproject, quat_to_rotmat, rotmat_to_quat
from semantic_gs_slam.render import Gaussians

PARAM_KEYS = ("means3D", "rgb_colors", "unnorm_rotations", "logit_opacities", "log_scales", "semantic_features")
MIN_CLASS_SCORE = 0.1  # a Gaussian whose largest class column is below this has no class (id 0)
SH_C0 = 0.28209479177387814


def palette(ids: np.ndarray | Tensor | int) -> np.ndarray:
    """Distinct semantic colours in [0, 1] for class ids (PASCAL-VOC style bit interleaving); id 0 is black."""
    ids = np.asarray(ids, dtype=np.int64)
    c = np.zeros(ids.shape + (3,), dtype=np.float64)
    v = ids.copy()
    for j in range(8):
        for ch in range(3):
            c[..., ch] += ((v >> ch) & 1) * (1 << (7 - j))
        v = v >> 3
    return c / 255.0


def _seed_normals(depth: Tensor, k: Intrinsics, smooth: int = 5) -> Tensor:
    """Camera-frame unit normals [H, W, 3] of a depth image (box-smoothed; zero where unknown or at
    depth discontinuities)."""
    from semantic_gs_slam.tracking.tracker import normal_map, smooth_depth

    d, ok = smooth_depth(depth, depth > 0, smooth)
    n, nok = normal_map(backproject(d, k.fx, k.fy, k.cx, k.cy), ok)
    return torch.where(nok[..., None], n, torch.zeros_like(n))


class GaussianMap:
    """Semantic Gaussian map with parameters as torch leaf tensors."""

    def __init__(self, device: str | torch.device = "cpu") -> None:
        self.device = torch.device(device)
        dev = self.device

        def z(*shape: int) -> Tensor:
            return torch.zeros(shape, device=dev)

        self.params: dict[str, Tensor] = {
            "means3D": z(0, 3), "rgb_colors": z(0, 3), "unnorm_rotations": z(0, 4),
            "logit_opacities": z(0, 1), "log_scales": z(0, 1), "semantic_features": z(0, 0)}
        self.class_slots: list[int] = []  # class id of each semantic_features column
        self.semantic_ids = torch.zeros(0, dtype=torch.int64, device=dev)  # [N] seed label
        self.timestep = torch.zeros(0, dtype=torch.int64, device=dev)  # [N] creating frame
        self.normals = torch.zeros(0, 3, device=dev)  # [N, 3] world unit normals (zero: unknown)
        self.votes = torch.zeros(0, 0, device=dev)  # [N, C] label votes over views (class_slots order)
        self.has_normals = False  # some row of normals was ever non-zero (kept on the host: no sync per render)
        for v in self.params.values():
            v.requires_grad_(True)

    def __len__(self) -> int:
        return int(self.params["means3D"].shape[0])

    def gaussians(self) -> Gaussians:
        """View of the parameters for the renderer (keeps the autograd link to :attr:`params`)."""
        p = self.params
        sem = p["semantic_features"] if self.class_slots else None
        return Gaussians(p["means3D"], p["unnorm_rotations"], p["log_scales"], p["logit_opacities"],
                         p["rgb_colors"], sem)

    def ensure_classes(self, ids: Tensor | np.ndarray) -> None:
        """Add a (zero) feature column for every class id > 0 in ``ids`` that has none yet."""
        found = torch.unique(ids).tolist() if isinstance(ids, Tensor) else np.unique(ids).tolist()  # one host copy
        new = sorted({int(i) for i in found if i > 0} - set(self.class_slots))
        if not new:
            return
        self.class_slots.extend(new)
        p = dict(self.params)
        f = p["semantic_features"].detach()
        p["semantic_features"] = torch.cat([f, torch.zeros(f.shape[0], len(new), device=f.device)], 1)
        self._set(p, self.semantic_ids, self.timestep)
        self.votes = torch.cat([self.votes, torch.zeros(self.votes.shape[0], len(new), device=self.votes.device)], 1)

    def one_hot(self, ids: Tensor) -> Tensor:
        """[..., C] one-hot rows of class ids in :attr:`class_slots` order (0 / unknown ids: all zero)."""
        dev = ids.device
        lut = torch.full((max(self.class_slots + [0]) + 1,), -1, dtype=torch.int64, device=dev)
        lut[torch.tensor(self.class_slots, dtype=torch.int64, device=dev)] = torch.arange(len(self.class_slots),
                                                                                          device=dev)
        ids = ids.long()
        slot = torch.where((ids >= 0) & (ids < len(lut)), lut[ids.clamp(0, len(lut) - 1)], -1)
        out = torch.zeros(ids.shape + (len(self.class_slots),), device=dev)
        hit = slot >= 0
        out[hit, slot[hit]] = 1.0
        return out

    def labels_from_features(self, feats: Tensor) -> Tensor:
        """Class id of each row of ``feats`` [..., C] (largest column; 0 when it is below MIN_CLASS_SCORE)."""
        if not self.class_slots:
            return torch.zeros(feats.shape[:-1], dtype=torch.int64, device=feats.device)
        best, arg = feats.detach().max(-1)
        ids = torch.tensor(self.class_slots, dtype=torch.int64, device=feats.device)[arg]
        return torch.where(best >= MIN_CLASS_SCORE, ids, torch.zeros_like(ids))

    def _set(self, new: dict[str, Tensor], ids: Tensor, ts: Tensor) -> None:
        self.params = {k: v.detach().contiguous().requires_grad_(True) for k, v in new.items()}
        self.semantic_ids, self.timestep = ids, ts

    def add(self, means: Tensor, rgb: Tensor, sem_ids: Tensor, radius: Tensor, frame: int,
            logit_opacity: float = 3.0, normals: Tensor | None = None) -> int:
        """Append Gaussians.

        Args:
            means: [M, 3] world centres.
            rgb: [M, 3] colours in [0, 1].
            sem_ids: [M] class ids.
            radius: [M] isotropic standard deviation (metres).
            frame: creating frame index.
            logit_opacity: initial opacity logit.
            normals: [M, 3] world unit normals (zero rows: unknown) or None.

        Returns:
            M.
        """
        m = means.shape[0]
        if m == 0:
            return 0
        dev = self.device
        means, rgb, sem_ids, radius = (t.to(dev) for t in (means, rgb, sem_ids, radius))
        self.ensure_classes(sem_ids)
        sem_col = self.one_hot(sem_ids)
        quat = torch.zeros(m, 4, device=dev)
        quat[:, 0] = 1.0
        new = {
            "means3D": means.float(), "rgb_colors": rgb.float(), "unnorm_rotations": quat,
            "logit_opacities": torch.full((m, 1), float(logit_opacity), device=dev),
            "log_scales": torch.log(radius.float().clamp_min(1e-4))[:, None], "semantic_features": sem_col}
        cat = {k: torch.cat([self.params[k].detach(), new[k]]) for k in PARAM_KEYS}
        self._set(cat, torch.cat([self.semantic_ids, sem_ids.long()]),
                  torch.cat([self.timestep, torch.full((m,), frame, dtype=torch.int64, device=dev)]))
        nrm = torch.zeros(m, 3, device=dev) if normals is None else normals.float().to(dev)
        self.normals = torch.cat([self.normals, nrm])
        self.votes = torch.cat([self.votes, sem_col])  # the seeding view's label is the first vote
        if normals is not None and not self.has_normals:
            self.has_normals = bool(nrm.abs().sum() > 0)
        return m

    def add_from_frame(self, rgb: Tensor, depth: Tensor, sem: Tensor | None, c2w: Tensor, k: Intrinsics,
                       mask: Tensor, stride: int, frame: int, radius_factor: float = 0.6,
                       logit_opacity: float = 3.0, fine: Tensor | None = None) -> int:
        """Seed Gaussians at every ``stride``-th pixel where ``mask`` holds.

        Args:
            rgb: [H, W, 3]; depth: [H, W] metres; sem: [H, W] ids or None; c2w: [4, 4];
            mask: [H, W] bool (valid depth and empty/occluding model).
            fine: [H, W] bool or None: of the masked pixels, these are seeded at every pixel with a
                one-pixel radius (small objects).

        Returns:
            Number of Gaussians added.
        """
        sel = torch.zeros_like(mask)
        sel[stride // 2::stride, stride // 2::stride] = True
        fine = torch.zeros_like(mask) if fine is None else fine
        sel = (sel | fine) & mask
        small = fine[sel]  # these get the one-pixel radius
        if not bool(sel.any()):
            return 0
        vmap = backproject(depth, k.fx, k.fy, k.cx, k.cy)  # [H, W, 3] camera
        pts = vmap[sel]  # [M, 3]
        world = pts @ c2w[:3, :3].T + c2w[:3, 3]
        normals = _seed_normals(depth, k)[sel] @ c2w[:3, :3].T  # [M, 3] world (zero: unknown)
        f = 0.5 * (k.fx + k.fy)
        radius = depth[sel] / f * radius_factor * torch.where(small, 1.0, float(stride))
        ids = sem[sel] if sem is not None else torch.zeros(world.shape[0], dtype=torch.int64, device=world.device)
        return self.add(world, rgb[sel], ids, radius, frame, logit_opacity, normals)

    def move_by_frame(self, starts: Tensor, transforms: Tensor) -> None:
        """Move Gaussians rigidly by the frame that created them (a loop closure's pose corrections).

        Args:
            starts: [K] ascending frame indices (int64): a Gaussian created at frame ``f`` takes the
                transform of the last start ``<= f`` (the first one when ``f`` is before all).
            transforms: [K, 4, 4] rigid world-frame corrections (new pose @ inverse of old pose).
        """
        if len(self) == 0:
            return
        dev = self.params["means3D"].device
        starts = starts.to(dev)
        tr = transforms.to(device=dev, dtype=torch.float32)
        slot = (torch.searchsorted(starts, self.timestep, right=True) - 1).clamp_min(0)  # [N]
        rot, trans = tr[slot, :3, :3], tr[slot, :3, 3]  # [N, 3, 3], [N, 3]
        p = {k: v.detach() for k, v in self.params.items()}
        p["means3D"] = (rot @ p["means3D"][:, :, None])[:, :, 0] + trans
        # [K, 4] quaternions of the few corrections, computed on the host (a loop closure, not a per-frame cost)
        qk = np.stack([rotmat_to_quat(r) for r in transforms[:, :3, :3].detach().cpu().numpy()])
        qc = torch.as_tensor(qk, dtype=torch.float32, device=dev)[slot]  # [N, 4]
        p["unnorm_rotations"] = _quat_mul(qc, p["unnorm_rotations"])
        self.normals = (rot @ self.normals[:, :, None])[:, :, 0]
        self._set(p, self.semantic_ids, self.timestep)

    def prune(self, min_opacity: float, max_scale: float) -> int:
        """Remove near-transparent or huge Gaussians; returns how many were removed."""
        with torch.no_grad():
            o = torch.sigmoid(self.params["logit_opacities"][:, 0])
            s = torch.exp(self.params["log_scales"]).max(1).values
            keep = (o >= min_opacity) & (s <= max_scale)
        removed = int((~keep).sum())
        if removed:
            self._set({k: v[keep] for k, v in self.params.items()}, self.semantic_ids[keep], self.timestep[keep])
            self.normals = self.normals[keep]
            self.votes = self.votes[keep]
        return removed

    def vote(self, sem: Tensor, depth: Tensor, w2c: Tensor, k: Intrinsics, tol_m: float = 0.03,
             tol_rel: float = 0.03) -> None:
        """Each Gaussian whose centre this frame sees (in the image, in front of the camera, within
        ``max(tol_m, tol_rel * depth)`` of the measured depth there: not occluded) votes for the label
        of its pixel; unlabelled pixels (0) and classes without a slot do not vote.

        Args:
            sem: [H, W] class ids; depth: [H, W] metres (0: missing); w2c: [4, 4] world-to-camera.
        """
        if len(self) == 0 or not self.class_slots:
            return
        with torch.no_grad():
            pc = self.params["means3D"].detach() @ w2c[:3, :3].T.float() + w2c[:3, 3].float()  # [N, 3] camera
            z = pc[:, 2]
            zs = z.clamp_min(1e-6)
            u = torch.round(k.fx * pc[:, 0] / zs + k.cx).long()
            v = torch.round(k.fy * pc[:, 1] / zs + k.cy).long()
            inside = (z > 1e-3) & (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height)
            uc, vc = u.clamp(0, k.width - 1), v.clamp(0, k.height - 1)
            d = depth[vc, uc]
            seen = inside & (d > 0) & ((z - d).abs() <= torch.clamp(tol_rel * d, min=tol_m))
            label = torch.where(seen, sem[vc, uc].long(), torch.zeros_like(u))
            slots = torch.tensor(self.class_slots, dtype=torch.int64, device=label.device)
            lut = torch.full((int(max(self.class_slots)) + 1,), -1, dtype=torch.int64, device=label.device)
            lut[slots] = torch.arange(len(slots), device=label.device)
            slot = torch.where(label < len(lut), lut[label.clamp(0, len(lut) - 1)], -1)  # -1: no vote
            onehot = torch.nn.functional.one_hot(slot.clamp_min(0), len(slots)).float()  # fixed shape: no sync
            self.votes = self.votes + onehot * (slot >= 0).float()[:, None]

    def voted_features(self, min_votes: float = 2.0) -> None:
        """Set the class columns of Gaussians with at least ``min_votes`` votes to their vote shares, so
        what the map renders (and :meth:`class_ids`) follows the majority over views, not the last
        keyframe's label (the semantic loss then refines them)."""
        if len(self) == 0 or not self.class_slots:
            return
        with torch.no_grad():
            total = self.votes.sum(1, keepdim=True)
            f = self.params["semantic_features"]
            f.copy_(torch.where(total >= min_votes, self.votes / total.clamp_min(1e-9), f))

    def class_ids(self) -> np.ndarray:
        """Semantic id of each Gaussian [N] = its largest optimised class column (0: none)."""
        if not self.class_slots or len(self) == 0:
            return self.semantic_ids.cpu().numpy().copy()
        return self.labels_from_features(self.params["semantic_features"]).cpu().numpy()

    # ------------------------------------------------------------------ files
    def to_arrays(self) -> dict[str, np.ndarray]:
        """Gaussian arrays in the SplaTAM / SGS-SLAM layout (float32; ids uint8 when they fit), plus
        ``semantic_features`` [N, C] and ``semantic_feature_ids`` [C]."""
        out = {k: v.detach().cpu().numpy().astype(np.float32) for k, v in self.params.items()}
        ids = self.class_ids()
        out["semantic_colors"] = palette(ids).astype(np.float32)
        out["semantic_feature_ids"] = np.array(self.class_slots, np.int64)
        out["semantic_ids"] = ids.astype(np.uint8) if (ids.size == 0 or ids.max() < 256) else ids.astype(np.int64)
        out["timestep"] = self.timestep.cpu().numpy().astype(np.float32)
        out["normals"] = self.normals.cpu().numpy().astype(np.float32)
        out["semantic_votes"] = self.votes.cpu().numpy().astype(np.float32)
        return out

    @staticmethod
    def from_arrays(a: dict[str, np.ndarray], device: str | torch.device = "cpu") -> GaussianMap:
        """Build a map from arrays (our files or SplaTAM / SGS-SLAM ``params.npz``).

        Raises:
            MapFormatError: ``means3D`` missing or rows that do not agree.
        """
        if "means3D" not in a:
            raise MapFormatError(f"params are missing 'means3D' (have {sorted(a)})")
        n = len(a["means3D"])
        m = GaussianMap(device)
        ids = np.asarray(a["semantic_ids"]).reshape(-1).astype(np.int64) if "semantic_ids" in a \
            else np.zeros(n, np.int64)
        if "semantic_features" in a and "semantic_feature_ids" in a:
            m.class_slots = [int(i) for i in np.asarray(a["semantic_feature_ids"]).reshape(-1)]
        else:  # SplaTAM / SGS-SLAM file (or an older one of ours): one-hot of the stored ids
            m.class_slots = sorted({int(i) for i in np.unique(ids) if i > 0})
        one_hot = m.one_hot(torch.as_tensor(ids, device=m.device)).cpu().numpy() if len(ids) == n \
            else np.zeros((n, len(m.class_slots)))
        defaults = {"rgb_colors": np.full((n, 3), 0.5), "unnorm_rotations": np.tile([1.0, 0, 0, 0], (n, 1)),
                    "logit_opacities": np.full((n, 1), 3.0), "log_scales": np.full((n, 1), np.log(0.01)),
                    "semantic_features": one_hot}
        params = {}
        for k in PARAM_KEYS:
            v = np.asarray(a[k]) if k in a and (k != "semantic_features" or "semantic_feature_ids" in a) \
                else defaults[k]
            if v.shape[0] != n:
                raise MapFormatError(f"'{k}' has {v.shape[0]} rows but means3D has {n}")
            params[k] = torch.as_tensor(np.asarray(v, dtype=np.float32), device=m.device)
        if params["semantic_features"].shape != (n, len(m.class_slots)):
            raise MapFormatError(f"'semantic_features' is {list(params['semantic_features'].shape)}, expected "
                                 f"[{n}, {len(m.class_slots)}] (one column per semantic_feature_ids entry)")
        if params["log_scales"].ndim == 1:
            params["log_scales"] = params["log_scales"][:, None]
        if len(ids) != n:
            raise MapFormatError(f"'semantic_ids' has {len(ids)} rows but means3D has {n}")
        ts = np.asarray(a["timestep"]).reshape(-1).astype(np.int64) if "timestep" in a else np.zeros(n, np.int64)
        m._set(params, torch.as_tensor(ids, device=m.device), torch.as_tensor(ts, device=m.device))
        nrm = np.asarray(a["normals"], np.float32) if "normals" in a else np.zeros((n, 3), np.float32)
        if nrm.shape != (n, 3):
            raise MapFormatError(f"'normals' is {list(nrm.shape)}, expected [{n}, 3]")
        m.normals = torch.as_tensor(nrm, device=m.device)
        m.has_normals = bool(np.abs(nrm).sum() > 0)
        votes = np.asarray(a["semantic_votes"], np.float32) if "semantic_votes" in a and "semantic_feature_ids" in a \
            else np.zeros((n, len(m.class_slots)), np.float32)
        if votes.shape != (n, len(m.class_slots)):
            raise MapFormatError(f"'semantic_votes' is {list(votes.shape)}, expected [{n}, {len(m.class_slots)}]")
        m.votes = torch.as_tensor(votes, device=m.device)
        return m


def save_params(path: str, gmap: GaussianMap, k: Intrinsics, est_w2c: list[np.ndarray],
                gt_w2c: list[np.ndarray | None], keyframes: list[int], timestamps: list[float] | None = None,
                views: list[np.ndarray] | None = None) -> None:
    """Write ``params.npz`` with the full SplaTAM / SGS-SLAM key set.

    Args:
        path: output file.
        gmap: the map.
        k: intrinsics.
        est_w2c: estimated world-to-camera pose per frame (T of them).
        gt_w2c: ground-truth world-to-camera per frame or None (stored as NaN).
        keyframes: keyframe frame indices.
        timestamps: each frame's time stamp (s), stored as ``timestamps`` [T] float64 (an extra key
            SplaTAM's readers ignore), so a trajectory can be matched to another clock's poses.
        views: camera-to-world poses [4, 4] the map was seen from (its keyframes', and those of the map a run
            started on), stored as ``view_c2w`` [K, 4, 4] float64 (another extra key): what
            :meth:`~semantic_gs_slam.slam.SLAM.from_map` relocalises against (:func:`map_views`).
    """

    a = gmap.to_arrays()
    t = len(est_w2c)
    rots = np.zeros((1, 4, t), np.float32)
    trans = np.zeros((1, 3, t), np.float32)
    for i, w in enumerate(est_w2c):
        rots[0, :, i] = rotmat_to_quat(w[:3, :3])
        trans[0, :, i] = w[:3, 3]
    gt = np.stack([g if g is not None else np.full((4, 4), np.nan) for g in gt_w2c]) if gt_w2c else np.zeros((0, 4, 4))
    a.update({
        "cam_unnorm_rots": rots, "cam_trans": trans,
        "intrinsics": np.array(k.as_matrix(), np.float32),
        "w2c": (est_w2c[0] if est_w2c else np.eye(4)).astype(np.float32),
        "org_width": np.array(k.width), "org_height": np.array(k.height),
        "gt_w2c_all_frames": gt.astype(np.float32),
        "keyframe_time_indices": np.array(keyframes, np.int64)})
    if timestamps is not None:
        a["timestamps"] = np.asarray(timestamps, np.float64)
    if views is not None:
        a["view_c2w"] = np.asarray(views, np.float64).reshape(-1, 4, 4)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    np.savez_compressed(path, **a)


def load_params(path: str) -> dict[str, np.ndarray]:
    """Read a ``params.npz`` (ours or SplaTAM / SGS-SLAM's) into a dict of arrays.

    Raises:
        MapFormatError: missing or unreadable file.
    """
    if not os.path.isfile(path):
        raise MapFormatError(f"map file not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise MapFormatError(f"{path}: not a readable .npz archive ({exc})") from exc


def trajectory_from_params(arrays: dict[str, np.ndarray]) -> list[np.ndarray]:
    """The estimated camera-to-world pose [4, 4] of every frame in a ``params.npz`` (:func:`load_params`; the
    SplaTAM keys ``cam_unnorm_rots`` [1, 4, T] and ``cam_trans`` [1, 3, T], world-to-camera).

    Raises:
        MapFormatError: the keys are missing or their shapes disagree.
    """
    try:
        q, t = np.asarray(arrays["cam_unnorm_rots"], np.float64)[0].T, np.asarray(arrays["cam_trans"], np.float64)[0].T
    except (KeyError, IndexError) as exc:
        raise MapFormatError(f"no camera trajectory in the map ({exc})") from exc
    if q.ndim != 2 or q.shape[1] != 4 or t.shape != (len(q), 3):
        raise MapFormatError(f"camera trajectory of shapes {q.shape} and {t.shape}, need [T, 4] and [T, 3]")
    w2c = np.tile(np.eye(4), (len(q), 1, 1))  # [T, 4, 4]
    w2c[:, :3, :3] = quat_to_rotmat(torch.as_tensor(q)).numpy()
    w2c[:, :3, 3] = t
    return list(np.linalg.inv(w2c))


def map_views(arrays: dict[str, np.ndarray]) -> list[np.ndarray]:
    """The camera-to-world poses [4, 4] a saved map (:func:`load_params`) was seen from: ``view_c2w`` when the file
    has it, else the keyframes' poses (``keyframe_time_indices`` into the trajectory), else every frame's pose
    (a SplaTAM / SGS-SLAM file, or ours before ``view_c2w``). Rows that are not finite rigid poses are dropped.

    Raises:
        MapFormatError: no poses at all, or keys of the wrong shape.
    """
    if "view_c2w" in arrays:
        v = np.asarray(arrays["view_c2w"], np.float64)
        if v.ndim != 3 or v.shape[1:] != (4, 4):
            raise MapFormatError(f"'view_c2w' is {list(v.shape)}, expected [K, 4, 4]")
        views = list(v)
    else:
        traj = trajectory_from_params(arrays) if "cam_trans" in arrays else []
        kf = [int(i) for i in np.asarray(arrays.get("keyframe_time_indices", []), np.int64).reshape(-1)
              if 0 <= int(i) < len(traj)]
        views = [traj[i] for i in kf] if kf else traj
    ok = [v for v in views if np.all(np.isfinite(v)) and abs(np.linalg.det(v[:3, :3]) - 1.0) < 1e-2]
    if not ok:
        raise MapFormatError("the map has no camera poses to relocalise against (no 'view_c2w', keyframes or "
                             "trajectory): pass the views explicitly")
    return ok


def save_semantic_json(path: str, classes: dict[int, str]) -> None:
    """``{"segmentation": [{"id": .., "class": ..}, ...]}`` (the seed's schema)."""
    with open(path, "w") as fh:
        json.dump({"segmentation": [{"id": int(i), "class": c} for i, c in sorted(classes.items())]}, fh, indent=1)
        fh.write("\n")


def load_semantic_json(path: str) -> dict[int, str]:
    """Inverse of :func:`save_semantic_json`; raises :class:`MapFormatError` on a bad file."""
    if not os.path.isfile(path):
        raise MapFormatError(f"semantic file not found: {path}")
    try:
        with open(path) as fh:
            return {int(e["id"]): str(e["class"]) for e in json.load(fh)["segmentation"]}
    except (ValueError, KeyError, TypeError) as exc:
        raise MapFormatError(f"{path}: not in the {{'segmentation': [{{'id', 'class'}}]}} schema ({exc})") from exc


def export_ply(path: str, gmap: GaussianMap) -> None:
    """Binary little-endian PLY in the standard 3DGS layout (x y z nx ny nz f_dc_0-2 f_rest_0-44 opacity
    scale_0-2 rot_0-3); degree-0 colour only, isotropic scales repeated, normals as seeded (0: unknown)."""
    a = gmap.to_arrays()
    n = len(a["means3D"])
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(45)] + \
        ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    data = np.zeros((n, len(names)), np.float32)
    data[:, 0:3] = a["means3D"]
    data[:, 3:6] = a["normals"]
    data[:, 6:9] = (a["rgb_colors"] - 0.5) / SH_C0
    data[:, 54] = a["logit_opacities"][:, 0]
    ls = a["log_scales"]
    data[:, 55:58] = ls if ls.shape[1] == 3 else np.repeat(ls, 3, 1)
    data[:, 58:62] = a["unnorm_rotations"]
    header = "ply\nformat binary_little_endian 1.0\n" + f"element vertex {n}\n" + \
        "".join(f"property float {p}\n" for p in names) + "end_header\n"
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(data.astype("<f4").tobytes())


def _quat_mul(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product of quaternions [..., 4] (w, x, y, z): the rotation ``a`` after ``b``."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)

"""Camera tracking: point-to-plane ICP of the live depth against the depth rendered from the map.

The model is rendered once at the constant-velocity guess; its depth (normalised by the silhouette,
used only where the silhouette is high) gives a vertex and a normal map in world coordinates.
Live points are associated projectively through the guess camera (KinectFusion-style) and the
pose is updated by Gauss-Newton on the point-to-plane residuals, coarse to fine. An optional
photometric refinement then runs Adam on the pose against colour and depth L1.
"""

from __future__ import annotations

import logging
import weakref
from dataclasses import dataclass

import torch
from torch import Tensor

from semantic_gs_slam.config import Intrinsics, RendererConfig, TrackingConfig, device_default
from semantic_gs_slam.devices import numba_available, require_cpu_kernel
from semantic_gs_slam.errors import TrackingError
from semantic_gs_slam.geometry import backproject, quat_to_rotmat, se3_exp
from semantic_gs_slam.render import Gaussians, RenderBackend, RenderOutput, select_backend
from semantic_gs_slam.tracking.icp_numba import icp_step_numba

log = logging.getLogger(__name__)


@dataclass
class TrackResult:
    """Outcome of tracking one frame."""

    c2w: Tensor  # [4, 4] float64
    residual: float  # RMS point-to-plane residual of the last iteration (m)
    inliers: int  # correspondences used in the last iteration
    agreement: float = float("nan")  # of the live points that land on the model at the final pose, the share
    # within 3 sigma (point-to-plane) of its surface: low when the pose is wrong (see TrackingConfig.lost_agreement)


def normal_map(v: Tensor, valid: Tensor) -> tuple[Tensor, Tensor]:
    """Normals of a vertex map by central-ish differences.

    Args:
        v: [H, W, 3] points. valid: [H, W] bool.

    Returns:
        normals [H, W, 3] (unit), valid [H, W] (neighbours valid too).
    """
    dx = torch.zeros_like(v)
    dy = torch.zeros_like(v)
    dx[:, :-1] = v[:, 1:] - v[:, :-1]
    dy[:-1] = v[1:] - v[:-1]
    n = torch.cross(dx, dy, dim=-1)
    norm = n.norm(dim=-1, keepdim=True)
    ok = valid.clone()
    ok[:, -1] = False
    ok[-1] = False
    ok[:, :-1] &= valid[:, 1:]
    ok[:-1] &= valid[1:]
    ok &= norm[..., 0] > 1e-12
    # no normals across depth discontinuities (neighbour steps longer than 5 % of the distance)
    lim = 0.05 * v.norm(dim=-1)
    ok &= (dx.norm(dim=-1) < lim) & (dy.norm(dim=-1) < lim)
    return n / norm.clamp_min(1e-12), ok


def plane_depth_features(means_c: Tensor, normals_c: Tensor, k: Intrinsics, min_cos: float = 0.2) -> Tensor:
    """Per-Gaussian features [N, 3] whose rendered blend gives depth along each pixel's ray.

    A Gaussian rendered with its centre depth ``Z`` is biased on oblique surfaces: a pixel ``d``
    pixels from the centre sees the surface at ``Z + d * dz/du``, not ``Z``. With a surface normal
    ``n`` the depth of the plane through the centre is, to first order around the centre pixel
    ``(u_c, v_c)``, ``z(u, v) = Z + a (u - u_c) + b (v - v_c)`` with ``a = -Z^2 n_x / (f_x n.mu)``,
    ``b = -Z^2 n_y / (f_y n.mu)``. Rendering ``F = [Z - a u_c - b v_c, a, b]`` as features and
    computing ``(F0 + u F1 + v F2) / silhouette`` per pixel blends these per-Gaussian planes instead
    of constant depths.

    Args:
        means_c: [N, 3] camera-frame centres. normals_c: [N, 3] camera-frame unit normals (zero rows:
            unknown). k: intrinsics. min_cos: planes seen more obliquely than this (|cos| of the angle
            between the normal and the viewing ray) fall back to the centre depth.

    Returns:
        [N, 3] features.
    """
    z = means_c[:, 2]
    nmu = (normals_c * means_c).sum(-1)
    cos = nmu.abs() / means_c.norm(dim=-1).clamp_min(1e-9)
    use = (cos >= min_cos) & (normals_c.norm(dim=-1) > 0.5)
    nmu = torch.where(use, nmu, torch.ones_like(nmu))
    a = torch.where(use, -z * z * normals_c[:, 0] / (k.fx * nmu), torch.zeros_like(z))
    b = torch.where(use, -z * z * normals_c[:, 1] / (k.fy * nmu), torch.zeros_like(z))
    uc = k.fx * means_c[:, 0] / z + k.cx
    vc = k.fy * means_c[:, 1] / z + k.cy
    return torch.stack([z - a * uc - b * vc, a, b], -1)


def plane_depth_image(feats_img: Tensor, silhouette: Tensor | None = None) -> Tensor:
    """Depth [H, W] from rendered :func:`plane_depth_features` [H, W, 3]: normalised by ``silhouette``
    when given, else the blend ``sum w_i z_i(u, v)`` (not normalised, like the renderer's depth)."""
    h, w = feats_img.shape[:2]
    v, u = torch.meshgrid(torch.arange(h, dtype=feats_img.dtype, device=feats_img.device),
                          torch.arange(w, dtype=feats_img.dtype, device=feats_img.device), indexing="ij")
    num = feats_img[..., 0] + u * feats_img[..., 1] + v * feats_img[..., 2]
    return num if silhouette is None else num / silhouette.clamp_min(1e-6)


def smooth_depth(depth: Tensor, valid: Tensor, size: int) -> tuple[Tensor, Tensor]:
    """Box-filter a depth image over its valid pixels (size x size window).

    Args:
        depth: [H, W] metres. valid: [H, W] bool. size: odd window edge.

    Returns:
        smoothed depth [H, W] and the pixels that stay valid (valid and with >= half the window valid).
    """
    import torch.nn.functional as F

    v = valid.to(depth.dtype)[None, None]
    num = F.avg_pool2d((depth * valid)[None, None], size, 1, size // 2, count_include_pad=False)
    den = F.avg_pool2d(v, size, 1, size // 2, count_include_pad=False)
    ok = valid & (den[0, 0] > 0.5)
    return torch.where(ok, num[0, 0] / den[0, 0].clamp_min(1e-6), torch.zeros_like(depth)), ok


def _so3_log(r: Tensor) -> Tensor:
    """Axis-angle [3] of a rotation [3, 3] (small-angle safe)."""
    c = ((r.diagonal().sum() - 1) / 2).clamp(-1.0, 1.0)
    th = torch.arccos(c)
    v = torch.stack([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    s = torch.where(th < 1e-6, torch.ones_like(th) * 0.5, th / (2 * torch.sin(th).clamp_min(1e-12)))
    return v * s


@dataclass
class _IcpModel:
    """The model side of one ICP problem, flattened to pixels [H*W, ...] (fixed shapes: one per image size)."""

    vm: Tensor  # [H*W, 3] world vertices (float64)
    nm: Tensor  # [H*W, 3] world unit normals
    nvalid: Tensor  # [H*W] bool: vertex and normal usable
    col: Tensor | None  # [H*W, 4] intensity, d/du, d/dv, usable (1/0); None: geometry only
    w2c_g: Tensor  # [4, 4] the camera the model was rendered from
    prior_w: Tensor  # [6, 6] information matrix of the prior toward the guess


@dataclass
class _IcpPoints:
    """The live points of one pyramid level, every ``stride``-th pixel, missing depth included (weight 0)."""

    lp: Tensor  # [M, 3] camera-frame points (float64; z = 0 where depth is missing)
    lvalid: Tensor  # [M] bool: depth present
    il: Tensor | None  # [M] live intensity, or None


def _solve_spd6(a: Tensor, b: Tensor) -> Tensor:
    """Solve ``a x = b`` for a symmetric positive definite [6, 6] ``a`` by Gauss-Jordan elimination without
    pivoting: fixed-shape tensor arithmetic only (no LAPACK call, no error check, no host synchronisation), so it
    can be captured in a CUDA graph. Tested against ``torch.linalg.solve``."""
    m = torch.cat([a, b[:, None]], 1)  # [6, 7]
    for i in range(6):
        row = m[i] / m[i, i]
        m = m - m[:, i:i + 1] * row[None]
        m = torch.cat([m[:i], row[None], m[i + 1:]], 0)
    return m[:, 6]


def icp_normal_equations(est: Tensor, pts: _IcpPoints, model: _IcpModel, k: Intrinsics, cfg: TrackingConfig,
                         photometric: bool) -> tuple[Tensor, Tensor, Tensor]:
    """The data terms of one ICP step from ``est`` [4, 4] (float64): the reference (any device).

    Every point takes part with a weight (0 for missing depth, off-image, no model vertex, too far): fixed
    shapes, no boolean indexing, so no host synchronisation and one graph per image size.
    :func:`semantic_gs_slam.tracking.icp_numba.normal_equations_numba` is the CPU fast path of the same sums.

    Returns:
        ``A`` [6, 6], ``b`` [6] of the Gauss-Newton system ``A xi = b`` and ``[correspondences, sum of squared
        geometric residuals, residuals within 3 sigma, points on a usable model pixel]`` [4] (float64, on the device).
    """
    dt = est.dtype
    w2c_g = model.w2c_g
    x = pts.lp @ est[:3, :3].T + est[:3, 3]  # [M, 3] world
    xc = x @ w2c_g[:3, :3].T + w2c_g[:3, 3]
    z = xc[:, 2].clamp_min(1e-6)
    uf = k.fx * xc[:, 0] / z + k.cx
    vf = k.fy * xc[:, 1] / z + k.cy
    u, v = torch.round(uf), torch.round(vf)
    inside = pts.lvalid & (xc[:, 2] > 1e-3) & (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height)
    # masks select with where, not by multiplying (NaN x 0 is NaN); a NaN coordinate is never inside, so its index is 0
    pix = torch.where(inside, v * k.width + u, torch.zeros_like(u)).long()  # [M]
    ok = inside & model.nvalid[pix]
    q, n = model.vm[pix], model.nm[pix]
    diff = x - q
    close = ok & (diff.norm(dim=-1) < cfg.icp_max_dist)
    mask = close.to(dt)
    r = torch.where(close, (diff * n).sum(-1), torch.zeros_like(mask))
    sg = cfg.icp_sigma_geo
    w = torch.where(r.abs() < sg, torch.ones_like(r), sg / r.abs().clamp_min(1e-30)) * mask * (cfg.geometric_weight
                                                                                               / (sg * sg))
    jac = torch.cat([torch.cross(x, n, dim=-1), n], -1)  # [M, 6]
    jw = torch.where(close[:, None], jac * w[:, None], torch.zeros_like(jac))
    jac = torch.where(close[:, None], jac, torch.zeros_like(jac))
    a = jw.T @ jac
    b = -(jw.T @ r)
    if photometric and model.col is not None and pts.il is not None:
        sc = cfg.icp_sigma_col
        inb = inside & (uf >= 0) & (uf < k.width - 1) & (vf >= 0) & (vf < k.height - 1)
        u0 = torch.where(inb, torch.floor(uf), torch.zeros_like(uf))
        v0 = torch.where(inb, torch.floor(vf), torch.zeros_like(vf))
        fu, fv = (uf - u0)[:, None], (vf - v0)[:, None]
        p00 = (v0 * k.width + u0).long()
        col = model.col
        smp = ((1 - fu) * (1 - fv) * col[p00] + fu * (1 - fv) * col[p00 + 1]
               + (1 - fu) * fv * col[p00 + k.width] + fu * fv * col[p00 + k.width + 1])  # [M, 4]
        use = inb & (smp[:, 3] > 0.999)
        mc = use.to(dt)
        rc = torch.where(use, smp[:, 0] - pts.il, torch.zeros_like(mc))
        # d(pixel)/d(camera point), camera point = R_gw (world point); world point moves by w x X + t
        zero = torch.zeros_like(z)
        du = torch.stack([k.fx / z, zero, -k.fx * xc[:, 0] / (z * z)], -1)
        dv = torch.stack([zero, k.fy / z, -k.fy * xc[:, 1] / (z * z)], -1)
        gvec = (smp[:, 1:2] * du + smp[:, 2:3] * dv) @ w2c_g[:3, :3]  # [M, 3] d I / d world point
        jc = torch.cat([torch.cross(x, gvec, dim=-1), gvec], -1)
        wc = torch.where(rc.abs() < sc, torch.ones_like(rc), sc / rc.abs().clamp_min(1e-30)) * mc * (
            cfg.photometric_weight / (sc * sc))
        jcw = torch.where(use[:, None], jc * wc[:, None], torch.zeros_like(jc))
        jc = torch.where(use[:, None], jc, torch.zeros_like(jc))
        a = a + jcw.T @ jc
        b = b - jcw.T @ rc
    sums = torch.stack([mask.sum(), (r * r).sum(), ((r.abs() < 3 * sg) & close).to(dt).sum(), ok.to(dt).sum()])
    return a, b, sums


def _icp_step(est: Tensor, pts: _IcpPoints, model: _IcpModel, k: Intrinsics, cfg: TrackingConfig,
              photometric: bool, solve=torch.linalg.solve, fast: bool = False) -> tuple[Tensor, Tensor]:
    """One Gauss-Newton step of :func:`icp` from ``est`` [4, 4] (float64).

    Args:
        fast: the step from :func:`semantic_gs_slam.tracking.icp_numba.icp_step_numba` (the compiled sums, then numpy)
            instead of this function's tensors; CPU tensors and numba needed.

    Returns:
        the new estimate [4, 4] and ``[correspondences, residual RMS (m), largest step component, agreement]`` [4]
        (float64, on the device).
    """
    if fast:  # the whole step compiled and in numpy (tracking_numba.icp_step_numba); the reference below
        return icp_step_numba(est, pts.lp, pts.lvalid, pts.il, model.vm, model.nm, model.nvalid, model.col,
                              model.w2c_g, model.prior_w, k, cfg, photometric)
    a, b, sums = icp_normal_equations(est, pts, model, k, cfg, photometric)
    dt = est.dtype
    # weak prior toward the guess: keeps directions the data leave free from drifting
    d = est @ model.w2c_g
    prior = torch.cat([_so3_log(d[:3, :3]), d[:3, 3]])
    a = a + model.prior_w
    b = b - model.prior_w @ prior
    a = a + torch.eye(6, dtype=dt, device=a.device) * (1e-9 * a.diagonal().mean())
    xi = solve(a, b)
    n_in = sums[0]
    stats = torch.stack([n_in, torch.sqrt(sums[1] / n_in.clamp_min(1.0)), xi.abs().max(),
                         sums[2] / sums[3].clamp_min(1.0)])
    return se3_exp(xi) @ est, stats


STEPS_PER_GRAPH = 4  # ICP steps per captured graph: one host copy per 4 steps instead of per step


def _icp_steps(est: Tensor, left: Tensor, pts: _IcpPoints, model: _IcpModel, k: Intrinsics, cfg: TrackingConfig,
               photometric: bool, steps: int, solve=_solve_spd6) -> tuple[Tensor, Tensor, Tensor]:
    """``steps`` :func:`_icp_step` s in a row with the eager loop's stopping rules kept on the device.

    Args:
        est: [4, 4] estimate. left: [] steps this level may still take (0: the level is over).

    Returns:
        the estimate after the accepted steps, the steps left (0 once a step is smaller than ``cfg.icp_min_step``
        or has too few correspondences), and ``[steps left, correspondences of a refused step (-1: none),
        correspondences, residual RMS, largest step, agreement]`` [6] of the last accepted step.
    """
    last = est.new_full((4,), float("nan"))
    refused = est.new_full((), -1.0)
    for _ in range(steps):
        new, st = _icp_step(est, pts, model, k, cfg, photometric, solve)
        active = left > 0
        fail = active & (st[0] < cfg.min_correspondences)
        accept = active & ~fail
        est = torch.where(accept, new, est)
        last = torch.where(accept, st, last)
        refused = torch.where(fail, st[0], refused)
        stop = fail | (accept & (st[2] < cfg.icp_min_step))
        left = torch.where(stop, torch.zeros_like(left), left - active.to(left.dtype))
    return est, left, torch.cat([torch.stack([left, refused]), last])


class _IcpGraph:
    """:data:`STEPS_PER_GRAPH` ICP steps (:func:`_icp_steps`) captured as one CUDA graph for one problem shape
    (image size, pyramid level, settings).

    A step of ICP is some 80 small kernels on a few thousand points: on a GPU its time is launch overhead and
    the host round trip of the convergence test, not arithmetic (14 ms of a 1200x680 frame, measured on an H200
    with one graph per step). Captured once, four steps are one graph launch and one host copy. Inputs are
    copied into static tensors (:meth:`load`, the live points once per level); the model's static tensors are
    shared by the graphs of every level and loaded once per problem (:class:`IcpGraphs`). The graph solves the
    6x6 systems with :func:`_solve_spd6` (LAPACK's solver checks its result on the host). With ``capture=False``
    the same chunks run eagerly (how the CPU tests check the chunking); ``tracking.cuda_graphs`` off runs the
    eager :func:`_icp_step` loop, the reference (a GPU test compares the two).
    """

    def __init__(self, pts: _IcpPoints, model: _IcpModel, k: Intrinsics, cfg: TrackingConfig, photometric: bool,
                 capture: bool = True):
        self.pts = _IcpPoints(*(None if t is None else t.clone() for t in (pts.lp, pts.lvalid, pts.il)))
        self.model = model  # static: owned by the cache, shared across levels, reloaded by load()
        self.k, self.cfg, self.photometric = k, cfg, photometric
        self.est = torch.linalg.inv(model.w2c_g)
        self.left = self.est.new_zeros(())
        self.graph = None
        if not capture:
            return
        dev = self.est.device
        with torch.cuda.device(dev):
            side = torch.cuda.Stream(device=dev)
            side.wait_stream(torch.cuda.current_stream(dev))
            with torch.cuda.stream(side):  # warm-up outside the capture (allocator, lazy initialisation)
                for _ in range(2):
                    self._chunk()
            torch.cuda.current_stream(dev).wait_stream(side)
            self.graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(self.graph, stream=torch.cuda.Stream(device=dev), capture_error_mode="thread_local"):
                est, left, self.stats = self._chunk()
                self.est.copy_(est)
                self.left.copy_(left)

    def _chunk(self) -> tuple[Tensor, Tensor, Tensor]:
        return _icp_steps(self.est, self.left, self.pts, self.model, self.k, self.cfg, self.photometric,
                          STEPS_PER_GRAPH)

    def load(self, pts: _IcpPoints) -> _IcpGraph:
        """Copy this level's live points into the static tensors (the model is loaded by :class:`IcpGraphs`)."""
        for dst, src in ((self.pts.lp, pts.lp), (self.pts.lvalid, pts.lvalid), (self.pts.il, pts.il)):
            if dst is not None:
                dst.copy_(src)
        return self

    def level(self, est: Tensor, iters: int) -> tuple[Tensor, int, float, float]:
        """Run one pyramid level (at most ``iters`` steps) from ``est``.

        Returns:
            the estimate, correspondences, residual RMS and agreement of its last step (NaN when none ran).

        Raises:
            TrackingError: a step found fewer than ``min_correspondences`` correspondences.
        """
        self.est.copy_(est)
        self.left.fill_(iters)
        n_in, rms, agree = 0, float("nan"), float("nan")
        for _ in range(-(-iters // STEPS_PER_GRAPH)):  # the steps left reach 0 by then; the bound is a backstop
            if self.graph is not None:
                with torch.cuda.device(self.est.device):
                    self.graph.replay()
                stats = self.stats
            else:
                est_c, left_c, stats = self._chunk()
                self.est.copy_(est_c)
                self.left.copy_(left_c)
            left, refused, n, rms_c, _, agree_c = stats.tolist()  # one host copy per chunk
            if refused >= 0:
                raise TrackingError(f"ICP found only {int(refused)} correspondences (< {self.cfg.min_correspondences})")
            if n == n:  # a step was accepted in this chunk (NaN: none)
                n_in, rms, agree = int(n), rms_c, agree_c
            if left <= 0:
                break
        return self.est.clone(), n_in, rms, agree


class IcpGraphs:
    """An engine's cache of captured ICP graphs (:class:`_IcpGraph`), one per problem shape and settings.

    Owned by one :class:`~semantic_gs_slam.slam.SLAM` and used from the thread that runs it: a graph's static
    inputs are loaded, then replayed, so two engines never share one. The model's static tensors (about 66 MB at
    1200x680 in float64) are kept once per image size and shared by the graphs of all pyramid levels. At most
    ``max_graphs`` graphs are kept (oldest dropped). Only CUDA problems get graphs; elsewhere :meth:`get` returns
    None and ICP runs its eager step loop.
    """

    def __init__(self, max_graphs: int = 8, capture: bool = True):
        self.max_graphs = max_graphs
        self.capture = capture  # False: CPU tests run the chunked path eagerly
        self._graphs: dict[tuple, _IcpGraph | None] = {}  # None: capture failed, that problem stays eager
        self._models: dict[tuple, _IcpModel] = {}  # static model tensors per image size
        self._loaded: dict[tuple, weakref.ref] = {}  # which problem's model they hold (loaded once, not per level)

    def __len__(self) -> int:
        return sum(g is not None for g in self._graphs.values())

    def get(self, pts: _IcpPoints, model: _IcpModel, k: Intrinsics, cfg: TrackingConfig,
            photometric: bool) -> _IcpGraph | None:
        """The graph for this problem, loaded with its inputs; None off CUDA, or when capturing failed (logged
        once; the eager step runs)."""
        if self.capture and pts.lp.device.type != "cuda":
            return None
        mkey = (pts.lp.device, tuple(model.vm.shape), model.col is not None)
        if mkey not in self._models:
            self._models[mkey] = _IcpModel(*(None if t is None else t.clone() for t in (
                model.vm, model.nm, model.nvalid, model.col, model.w2c_g, model.prior_w)))
            self._loaded[mkey] = weakref.ref(model)
        elif (self._loaded[mkey])() is not model:
            static = self._models[mkey]
            for dst, src in ((static.vm, model.vm), (static.nm, model.nm), (static.nvalid, model.nvalid),
                             (static.col, model.col), (static.w2c_g, model.w2c_g), (static.prior_w, model.prior_w)):
                if dst is not None:
                    dst.copy_(src)
            self._loaded[mkey] = weakref.ref(model)
        key = (mkey, tuple(pts.lp.shape), pts.il is not None, k, cfg.icp_max_dist, cfg.icp_sigma_geo,
               cfg.icp_sigma_col, cfg.geometric_weight, cfg.photometric_weight, cfg.min_correspondences,
               cfg.icp_min_step, photometric)
        if key not in self._graphs:
            if len(self._graphs) >= self.max_graphs:
                self._graphs.pop(next(iter(self._graphs)))
            try:
                self._graphs[key] = _IcpGraph(pts, self._models[mkey], k, cfg, photometric, self.capture)
            except Exception as exc:  # noqa: BLE001 - any capture failure falls back to the eager reference
                log.warning("ICP: capturing a CUDA graph failed (%s: %s); running the step eagerly",
                            type(exc).__name__, exc)
                self._graphs[key] = None
        graph = self._graphs[key]
        return None if graph is None else graph.load(pts)


def icp_uses_numba(cfg: TrackingConfig, device: torch.device) -> bool:
    """Whether :func:`icp` sums its steps in the compiled CPU kernel (``cfg.icp_backend``).

    Raises:
        BackendUnavailableError: ``numba`` asked for without numba, or for tensors off the CPU.
    """
    if cfg.icp_backend == "numba":
        require_cpu_kernel("tracking.icp_backend", device)
        return True
    return cfg.icp_backend == "auto" and device.type == "cpu" and numba_available()


def icp(model_depth: Tensor, model_valid: Tensor, guess_c2w: Tensor, live_depth: Tensor, k: Intrinsics,
        cfg: TrackingConfig, model_rgb: Tensor | None = None, live_rgb: Tensor | None = None,
        start_c2w: Tensor | None = None, graphs: IcpGraphs | None = None) -> TrackResult:
    """Point-to-plane ICP (plus an optional photometric term) of a live frame against a model frame
    rendered at ``guess_c2w``.

    The joint Gauss-Newton minimises ``sum w_g (n . (T x - q))^2 / s_g^2 + sum w_c (I_m(pi(T x)) - I_l)^2 / s_c^2``
    with Huber weights; the photometric term pins down the directions that planes leave free (a camera
    sliding along a wall). Each step (:func:`_icp_step`) has fixed shapes; one host copy per step (the
    convergence test and the correspondence count), or per chunk of :data:`STEPS_PER_GRAPH` steps when they
    are replayed from a CUDA graph (``graphs``).

    Args:
        model_depth: [H, W] metres (rendered at the guess pose).
        model_valid: [H, W] bool.
        guess_c2w: [4, 4] float64 pose the model was rendered at (also the start).
        live_depth: [H, W] metres, 0 = missing.
        k: intrinsics.
        cfg: tracking settings.
        model_rgb: [H, W, 3] colour rendered at the guess pose, or None (geometry only).
        live_rgb: [H, W, 3] live colour, or None.
        start_c2w: [4, 4] initial estimate (default: ``guess_c2w``).
        graphs: the engine's captured steps (:class:`IcpGraphs`), used on CUDA when ``cfg.cuda_graphs``; None:
            the eager step loop.

    Returns:
        :class:`TrackResult`.

    Raises:
        TrackingError: fewer than ``cfg.min_correspondences`` associations.
    """
    dt = torch.float64
    dev = live_depth.device
    g = guess_c2w.to(dt)
    if cfg.normal_smoothing > 1:
        model_depth, model_valid = smooth_depth(model_depth, model_valid, cfg.normal_smoothing)
    vm_c = backproject(model_depth.to(dt), k.fx, k.fy, k.cx, k.cy)
    vm = vm_c @ g[:3, :3].T + g[:3, 3]  # world vertex map [H, W, 3]
    nm, nvalid = normal_map(vm, model_valid)
    live_all = backproject(live_depth.to(dt), k.fx, k.fy, k.cx, k.cy)
    use_col = model_rgb is not None and live_rgb is not None and cfg.photometric_weight > 0
    col = il_all = None
    if use_col:
        im = model_rgb.to(dt).mean(-1)  # [H, W] intensity
        il_all = live_rgb.to(dt).mean(-1)
        gx = torch.zeros_like(im)
        gy = torch.zeros_like(im)
        gx[:, 1:-1] = 0.5 * (im[:, 2:] - im[:, :-2])
        gy[1:-1] = 0.5 * (im[2:] - im[:-2])
        okm = model_valid.clone()
        okm[:, 1:-1] &= model_valid[:, 2:] & model_valid[:, :-2]
        okm[1:-1] &= model_valid[2:] & model_valid[:-2]
        okm[:, [0, -1]] = False
        okm[[0, -1]] = False
        col = torch.stack([im, gx, gy, okm.to(dt)], -1).reshape(-1, 4)  # [H*W, 4]
    p_w = torch.diag(torch.tensor([1 / cfg.prior_sigma_rot**2] * 3 + [1 / cfg.prior_sigma_trans**2] * 3, dtype=dt,
                                  device=dev))
    model = _IcpModel(vm.reshape(-1, 3), nm.reshape(-1, 3), nvalid.reshape(-1), col, torch.linalg.inv(g), p_w)
    est = g.clone() if start_c2w is None else start_c2w.to(dt).clone()
    res_rms, n_in, agree = float("nan"), 0, float("nan")
    iters = cfg.icp_iters if cfg.icp_iters is not None else device_default("tracking", "icp_iters", dev.type)
    fast = icp_uses_numba(cfg, dev)
    base = max(1, round(k.width / cfg.icp_row_points))  # live points per row at the finest level
    for level in reversed(range(cfg.icp_levels)):
        stride = base * 2**level
        lp = live_all[::stride, ::stride].reshape(-1, 3)
        pts = _IcpPoints(lp, lp[:, 2] > 0, il_all[::stride, ::stride].reshape(-1) if use_col else None)
        photometric = use_col and level == 0  # the photometric term only at the finest level (small basin)
        graph = graphs.get(pts, model, k, cfg, photometric) if graphs is not None and cfg.cuda_graphs else None
        if graph is not None:
            if iters > 0:
                est, n_in, res_rms, agree = graph.level(est, iters)
            continue
        for _ in range(iters):
            new, stats = _icp_step(est, pts, model, k, cfg, photometric, fast=fast)
            n, rms, step, ag = stats.tolist()  # one host copy per step
            n_in = int(n)
            if n_in < cfg.min_correspondences:
                raise TrackingError(f"ICP found only {n_in} correspondences (< {cfg.min_correspondences})")
            est, res_rms, agree = new, rms, ag
            if step < cfg.icp_min_step:
                break
    return TrackResult(est, res_rms, n_in, agree)


def _quat_from_rot(r: Tensor) -> Tensor:
    from semantic_gs_slam.geometry import rotmat_to_quat

    return torch.as_tensor(rotmat_to_quat(r.detach().cpu().numpy()), device=r.device)


def photometric_loss(g: Gaussians, w2c: Tensor, rgb: Tensor, depth: Tensor, k: Intrinsics, rcfg: RendererConfig,
                     min_silhouette: float, backend: RenderBackend | None = None) -> Tensor:
    """Sum of L1 depth + 0.5 L1 colour (both normalised by the silhouette) over pixels with valid depth and
    silhouette > ``min_silhouette`` (0 when no pixel qualifies); a fixed-shape computation (a mask
    multiplies, no boolean indexing), so no host synchronisation."""
    out = (backend or select_backend(rcfg, g.means.device))(g, w2c, k, rcfg)
    return photometric_loss_of(out, rgb, depth, min_silhouette)


def photometric_loss_of(out: RenderOutput, rgb: Tensor, depth: Tensor, min_silhouette: float) -> Tensor:
    """:func:`photometric_loss` of a rendered view ``out`` against ``rgb`` [H, W, 3] and ``depth`` [H, W]."""
    m = ((out.silhouette.detach() > min_silhouette) & (depth > 0)).to(depth.dtype)
    sil = out.silhouette.clamp_min(1e-6)
    l_depth = ((out.depth / sil - depth).abs() * m).sum()
    return l_depth + 0.5 * ((out.rgb / sil[..., None] - rgb).abs().sum(-1) * m).sum()


def w2c_from_quat_trans(q: Tensor, t: Tensor) -> Tensor:
    """[4, 4] world-to-camera pose from an (unnormalised) quaternion [4] (wxyz) and a translation [3]."""
    bottom = torch.nn.functional.pad(torch.ones_like(t[:1]), (3, 0))[None]  # [[0, 0, 0, 1]], no host copy
    return torch.cat([torch.cat([quat_to_rotmat(q), t[:, None]], 1), bottom], 0)


def photometric_refine(g: Gaussians, c2w: Tensor, rgb: Tensor, depth: Tensor, k: Intrinsics,
                       rcfg: RendererConfig, cfg: TrackingConfig, backend: RenderBackend | None = None) -> Tensor:
    """Refine a pose with Adam (SplaTAM-style) on :func:`photometric_loss`.

    Args:
        g: the map (detached parameters are fine).
        c2w: [4, 4] start pose. rgb: [H, W, 3]. depth: [H, W].

    Returns:
        [4, 4] float64 refined camera-to-world pose (the iterate with the lowest loss).
    """
    w2c0 = torch.linalg.inv(c2w.double())
    q = _quat_from_rot(w2c0[:3, :3]).float().requires_grad_(True)
    t = w2c0[:3, 3].float().clone().requires_grad_(True)
    opt = torch.optim.Adam([{"params": [q], "lr": cfg.photometric_lr_rot},
                            {"params": [t], "lr": cfg.photometric_lr_trans}])
    gd = Gaussians(*(x.detach() for x in (g.means, g.quats, g.log_scales, g.logit_opacities, g.rgb)), None)
    backend = backend or select_backend(rcfg, g.means.device)
    # the best iterate is kept on the device (no host round trip per iteration)
    best_loss = torch.full((), float("inf"), device=q.device)
    best_q, best_t = q.detach().clone(), t.detach().clone()
    for _ in range(cfg.photometric_iters):
        loss = photometric_loss(gd, w2c_from_quat_trans(q, t), rgb, depth, k, rcfg, cfg.min_silhouette, backend)
        with torch.no_grad():
            better = loss.detach() < best_loss
            best_loss = torch.where(better, loss.detach(), best_loss)
            best_q = torch.where(better, q.detach(), best_q)
            best_t = torch.where(better, t.detach(), best_t)
        opt.zero_grad()
        loss.backward()
        with torch.device(q.device):  # some torch versions (2.11) make Adam's step counter on the default device
            opt.step()
    with torch.no_grad():
        w2c = w2c_from_quat_trans(best_q.double(), best_t.double())
    return torch.linalg.inv(w2c)

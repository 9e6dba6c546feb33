"""The tracking's compiled CPU kernel (numba): one pass of an ICP step's normal equations.

Imported only by :mod:`semantic_gs_slam.tracking.icp_numba` when it first runs, so the engine imports without numba.
Plain numpy-in, numpy-out functions at module level, so numba's on-disk cache (``cache=True``) finds them again in
the next process (defined inside another function, they were compiled anew in every process).
Its PyTorch reference and how they are compared: :mod:`semantic_gs_slam.tracking.icp_numba`.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def icp_accumulate(est, w2c_g, lp, lvalid, il, vm, nm, nvalid, col, fx, fy, cx, cy, width, height, max_dist, sg,
               sg_z2, w_geo, photometric, sc, w_col, a, b, stats, gate_z2):
    jac = np.zeros(6)
    n_close = 0.0
    rr = 0.0
    n_agree = 0.0
    n_ok = 0.0
    for m in range(lp.shape[0]):
        if not lvalid[m]:
            continue
        p0, p1, p2 = lp[m, 0], lp[m, 1], lp[m, 2]
        x0 = est[0, 0] * p0 + est[0, 1] * p1 + est[0, 2] * p2 + est[0, 3]
        x1 = est[1, 0] * p0 + est[1, 1] * p1 + est[1, 2] * p2 + est[1, 3]
        x2 = est[2, 0] * p0 + est[2, 1] * p1 + est[2, 2] * p2 + est[2, 3]
        c0 = w2c_g[0, 0] * x0 + w2c_g[0, 1] * x1 + w2c_g[0, 2] * x2 + w2c_g[0, 3]
        c1 = w2c_g[1, 0] * x0 + w2c_g[1, 1] * x1 + w2c_g[1, 2] * x2 + w2c_g[1, 3]
        c2 = w2c_g[2, 0] * x0 + w2c_g[2, 1] * x1 + w2c_g[2, 2] * x2 + w2c_g[2, 3]
        if not c2 > 1e-3:  # (also false for NaN)
            continue
        z = c2
        uf = fx * c0 / z + cx
        vf = fy * c1 / z + cy
        if not (uf > -1.0 and uf < width + 1.0 and vf > -1.0 and vf < height + 1.0):
            continue
        u = np.rint(uf)  # round half to even, as torch.round
        v = np.rint(vf)
        if u < 0 or u >= width or v < 0 or v >= height:
            continue
        pix = int(v) * width + int(u)
        if nvalid[pix]:
            n_ok += 1.0
            n0, n1, n2 = nm[pix, 0], nm[pix, 1], nm[pix, 2]
            d0, d1, d2 = x0 - vm[pix, 0], x1 - vm[pix, 1], x2 - vm[pix, 2]
            if np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) < max(max_dist, gate_z2 * z * z):
                r = d0 * n0 + d1 * n1 + d2 * n2
                ar = abs(r)
                s = max(sg, sg_z2 * z * z)  # the residual's scale: a depth sensor's noise grows with depth squared
                w = (1.0 if ar < s else s / max(ar, 1e-30)) * (w_geo / (s * s))
                jac[0] = x1 * n2 - x2 * n1
                jac[1] = x2 * n0 - x0 * n2
                jac[2] = x0 * n1 - x1 * n0
                jac[3], jac[4], jac[5] = n0, n1, n2
                for i in range(6):
                    wi = w * jac[i]
                    b[i] -= wi * r
                    for j in range(i + 1):
                        a[i, j] += wi * jac[j]
                n_close += 1.0
                rr += r * r
                if ar < 3 * s:
                    n_agree += 1.0
        if photometric and uf >= 0 and uf < width - 1 and vf >= 0 and vf < height - 1:
            u0 = np.floor(uf)
            v0 = np.floor(vf)
            fu, fv = uf - u0, vf - v0
            q00 = int(v0) * width + int(u0)
            w00, w01, w10, w11 = (1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv
            q01, q10, q11 = q00 + 1, q00 + width, q00 + width + 1
            s0 = w00 * col[q00, 0] + w01 * col[q01, 0] + w10 * col[q10, 0] + w11 * col[q11, 0]
            s1 = w00 * col[q00, 1] + w01 * col[q01, 1] + w10 * col[q10, 1] + w11 * col[q11, 1]
            s2 = w00 * col[q00, 2] + w01 * col[q01, 2] + w10 * col[q10, 2] + w11 * col[q11, 2]
            s3 = w00 * col[q00, 3] + w01 * col[q01, 3] + w10 * col[q10, 3] + w11 * col[q11, 3]
            if s3 > 0.999:
                rc = s0 - il[m]
                # d I / d camera point, then to the world point through the model camera's rotation
                e0 = s1 * fx / z
                e1 = s2 * fy / z
                e2 = -(s1 * fx * c0 + s2 * fy * c1) / (z * z)
                g0 = e0 * w2c_g[0, 0] + e1 * w2c_g[1, 0] + e2 * w2c_g[2, 0]
                g1 = e0 * w2c_g[0, 1] + e1 * w2c_g[1, 1] + e2 * w2c_g[2, 1]
                g2 = e0 * w2c_g[0, 2] + e1 * w2c_g[1, 2] + e2 * w2c_g[2, 2]
                jac[0] = x1 * g2 - x2 * g1
                jac[1] = x2 * g0 - x0 * g2
                jac[2] = x0 * g1 - x1 * g0
                jac[3], jac[4], jac[5] = g0, g1, g2
                arc = abs(rc)
                wc = (1.0 if arc < sc else sc / max(arc, 1e-30)) * (w_col / (sc * sc))
                for i in range(6):
                    wi = wc * jac[i]
                    b[i] -= wi * rc
                    for j in range(i + 1):
                        a[i, j] += wi * jac[j]
    for i in range(6):
        for j in range(i):
            a[j, i] = a[i, j]
    stats[0] = n_close
    stats[1] = rr
    stats[2] = n_agree
    stats[3] = n_ok

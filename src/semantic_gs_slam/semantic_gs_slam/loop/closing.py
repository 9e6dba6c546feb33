"""Loop closure inside the engine: at a new keyframe, register it against old overlapping keyframes
(:func:`~semantic_gs_slam.loop.detection.find_loops`), add verified loops to the pose graph
(:mod:`semantic_gs_slam.loop.posegraph`), optimise it and move the poses and the Gaussians.

:class:`LoopClosing` is a mixin of :class:`~semantic_gs_slam.slam.SLAM`; the methods use the engine's state:
``cfg``, ``k``, ``device``, ``map``, ``keyframes``, ``poses``, ``odom_poses``, ``edges``, ``loops``,
``_icp_graphs`` and ``_move_frames``.
"""

from __future__ import annotations

import logging

import numpy as np
import torch
from torch import Tensor

from semantic_gs_slam.geometry import pose_error
from semantic_gs_slam.loop.detection import LoopMatch, find_loops
from semantic_gs_slam.loop.posegraph import Edge
from semantic_gs_slam.loop.posegraph import optimise as optimise_graph

log = logging.getLogger("semantic_gs_slam")


class LoopClosing:
    """Loop detection and correction of :class:`~semantic_gs_slam.slam.SLAM` (a mixin)."""

    def _close_loop(self, idx: int, depth: Tensor) -> str:
        """Loop closure at a new keyframe (before it is added): register it against its most overlapping old
        keyframes (``loop.candidates``); verified drift is logged, added to the pose graph as loop edges and
        spread over the keyframes (poses, keyframe poses and the Gaussians they created move together).
        Returns a note for the frame's log."""
        lc = self.cfg.loop
        n_kf = len(self.keyframes)
        if not lc.enabled or n_kf < 2 or n_kf % lc.check_every or \
                (self.odom_poses[idx] is not None and not lc.with_odometry):
            return ""
        matches = find_loops(depth, self.poses[idx], idx, self.keyframes, self.k, lc, self.cfg.tracking,
                             [self.poses[kf.index] for kf in self.keyframes], self._icp_graphs)
        notes, correct, usable = [], [], []
        for m in matches:
            verdict = m.verdict(lc)
            notes.append(f"loop with frame {m.frame}: {verdict} ({m.correction_m * 100:.1f} cm, "
                         f"{m.correction_deg:.2f} deg, agreement {m.agreement_before:.0%} -> {m.agreement_after:.0%})")
            correct += [m] if verdict == "correct" else []
            usable += [m] if verdict in ("correct", "consistent") else []
        if correct:
            m = correct[0]
            log.warning("frame %d: drift found against the keyframe of frame %d: %.1f cm, %.2f deg; correcting the "
                        "trajectory and the map", idx, m.frame, m.correction_m * 100, m.correction_deg)
            self._apply_loop(idx, usable)  # verified registrations that agree with the tracking constrain too
        return "; ".join(notes)

    def _apply_loop(self, idx: int, matches: list[LoopMatch]) -> None:
        """Add the current keyframe and the loop edges to the pose graph, optimise it, move poses and Gaussians."""
        lc = self.cfg.loop
        old = [self.poses[kf.index] for kf in self.keyframes] + [self.poses[idx]]  # host copies of the kf poses
        cur = len(old) - 1
        loops = [Edge(m.candidate, cur, np.linalg.inv(old[m.candidate]) @ m.c2w, lc.loop_sigma_rot,
                      lc.loop_sigma_trans, "loop") for m in matches]
        seq = Edge(cur - 1, cur, np.linalg.inv(old[cur - 1]) @ old[cur], lc.sigma_rot, lc.sigma_trans)
        new, cost0, cost1 = optimise_graph(old, self.edges + [seq] + loops, fixed=0, iters=5)
        self.edges.extend(loops)  # the loop edges stay; the sequential one is added with the keyframe
        corr = [n @ np.linalg.inv(o) for n, o in zip(new, old, strict=True)]
        if lc.own_correction_sigmas > 0 and cur > 0:  # a difference within the loop edges' noise is noise
            extra_m, extra_deg = pose_error(corr[cur - 1] @ old[cur], new[cur])
            if extra_m < lc.own_correction_sigmas * lc.loop_sigma_trans and \
                    np.radians(extra_deg) < lc.own_correction_sigmas * lc.loop_sigma_rot:
                corr[cur] = corr[cur - 1]
                new[cur] = corr[cur] @ old[cur]
        starts = [kf.index for kf in self.keyframes] + [idx]
        self._move_frames(starts, corr)
        for kf, n in zip(self.keyframes, new[:-1], strict=False):
            kf.c2w = torch.as_tensor(n, device=self.device)
        self.map.move_by_frame(torch.as_tensor(starts, dtype=torch.int64, device=self.device),
                               torch.as_tensor(np.stack(corr), dtype=torch.float32, device=self.device))
        et, er = pose_error(np.eye(4), corr[-1])
        m = max(matches, key=lambda x: x.correction_m)
        self.loops.append({"frame": idx, "with_frame": m.frame, "found_cm": m.correction_m * 100,
                           "found_deg": m.correction_deg, "moved_cm": et * 100, "moved_deg": er,
                           "agreement_before": m.agreement_before, "agreement_after": m.agreement_after,
                           "edges": len(matches), "graph_cost_before": cost0, "graph_cost_after": cost1})

"""The frame-rate front end inside the engine (``tracking.frontend = "keyframe"``): a mixin of
:class:`~semantic_gs_slam.slam.SLAM`.

Every frame is tracked (:func:`~semantic_gs_slam.tracking.frontend.track`) against the latest keyframe's reference
model: the keyframe's own sensor depth and colour at its latest pose (moved when the mapping back end corrects it:
loop closure). Nothing here reads the Gaussian map, so tracking runs beside a mapping thread.

A frame the reference does not track to a trusted pose (:class:`~semantic_gs_slam.tracking.frontend.TrackQuality`)
is tracked again with more steps against the frame before it, which then becomes the reference (a fast move); a frame
still not trusted is lost: it keeps the previous pose and is not mapped. Lost frames try to relocalise (the first,
then every ``tracking.relocalise_every``-th) against the keyframes ranked by a thumbnail of depth and intensity plus
the one nearest the last trusted pose, from their poses and perturbed guesses that widen when the near ones fail. A
relocalised pose must then be trusted on ``tracking.relocalise_confirm`` frames in a row before mapping resumes; a
frame that fails meanwhile is lost again.

While lost (``tracking.lost_segment``), the lost frames are tracked among themselves: a *lost segment* starts at the
first lost frame, posed at the guess it had (constant velocity, or the odometry's), and each next lost frame is
tracked against the segment's latest reference frame (a frame it does not track goes on from the constant-velocity
guess and becomes the reference). Its pose is then the segment's (the camera's motion since the loss, from a guessed
start) instead of the frozen last pose, and it is one more guess for relocalisation. When the
map takes the camera back (recovered), the whole segment is moved by the one rigid correction that puts its
relocalised frame on its relocalised pose: the lost stretch is re-posed in the map's frame. Lost frames are not mapped
as they come; once joined, the segment's views (the frames that became its reference) join the backlog that the
refinement maps (``SLAM._join_lost_views``).

A camera that turns to ground no keyframe saw is not taken back by the map until it returns. After
``tracking.lost_resume_after`` lost frames, when its lost segment tracked its last ``relocalise_confirm`` frames and
started from a trustworthy guess (the odometry's, or constant velocity extrapolated in full, over at most
``velocity_max_scale`` steps: not after a stall or a jump in time, where the guess is no pose), mapping *resumes* on
the segment's own track (pose source ``resumed``): the segment's frames keep their poses, its views join the
backlog, and the frame becomes a keyframe. The new ground is then mapped where the segment puts it, the first lost
frame's guess being its anchor. Every ``tracking.reanchor_every`` frames a frame of the resumed track is relocalised
against the keyframes from before the loss; a correction that the next frame confirms is due (``reanchor_due``), and
``SLAM.add_frame`` moves the resumed track, its keyframes and their Gaussians by it into the map's frame.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from dataclasses import dataclass, replace

import numpy as np

from semantic_gs_slam.geometry import pose_error
from semantic_gs_slam.tracking.frontend import (
    FrontendConfig,
    LiveFrame,
    ReferenceModel,
    RelocalisationError,
    TrackResult,
    build_reference,
    downsample_frame,
    prepare_live,
    relocalise,
    track,
)

log = logging.getLogger("semantic_gs_slam")

_THUMB = (15, 20)  # rows, columns of the relocalisation thumbnails
AUTO_MIN_WIDTH = 320  # tracking.frontend_downsample 0: the front end's image is halved while it stays this wide
#: a resumed track (tracking.reanchor_every) whose relocalisation in the keyframes from before the loss is this close
#: to its tracked pose (metres, degrees) is in the map's frame already: nothing is moved (loop closure sees the rest)
REANCHOR_MIN = (0.10, 5.0)
#: a correction is applied once a second relocalisation, on the next frame, finds the same one within this (m, deg)
REANCHOR_AGREE = (0.05, 3.0)
#: metres; the association gate of a re-anchoring try on the coarsest level (a lost frame's: FrontendConfig.max_dist)
REANCHOR_COARSE_GATE = 0.4


@dataclass
class KeyframeView:
    """What the front end keeps of a keyframe (tracking thread only)."""

    index: int  # frame index
    depth: np.ndarray  # [H, W] float64 metres
    rgb: np.ndarray  # [H, W, 3] float64 in [0, 1]
    thumb: np.ndarray  # [2, 15, 20] depth (m) and intensity at a coarse grid


@dataclass
class LostSegment:
    """Lost frames tracked among themselves (tracking thread only): poses in ``SLAM.poses`` hang from the first
    frame's guessed pose."""

    frames: list[int]  # the segment's frames, in order (the last one tracked into it last)
    ref: ReferenceModel  # the latest reference frame, at its segment pose
    views: list[int]  # the frames that became its reference (new views: mapped once the segment is joined)
    anchored: bool = False  # its first frame's guess is trustworthy (no stall): mapping may resume on its track
    trusted_run: int = 0  # its latest frames trusted against its reference, in a row


def thumbnail(depth: np.ndarray, rgb: np.ndarray) -> np.ndarray:
    """[2, 15, 20]: depth and intensity sampled on a 15 x 20 grid of pixel centres (a cheap place signature)."""
    h, w = depth.shape
    rows = ((np.arange(_THUMB[0]) + 0.5) * h / _THUMB[0]).astype(int)
    cols = ((np.arange(_THUMB[1]) + 0.5) * w / _THUMB[1]).astype(int)
    return np.stack([depth[np.ix_(rows, cols)], rgb[np.ix_(rows, cols)].mean(-1)])


def thumbnail_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Mean depth difference (m) plus mean intensity difference where both have depth; 1 per pixel where one has."""
    both = (a[0] > 0) & (b[0] > 0)
    one = (a[0] > 0) != (b[0] > 0)
    n = max(int(both.sum() + one.sum()), 1)
    return float((np.abs(a[0] - b[0])[both].sum() + np.abs(a[1] - b[1])[both].sum() + one.sum()) / n)


class KeyframeTracking:
    """Per-frame tracking against keyframe references, lost / relocalised / recovered states (a mixin)."""

    def _fe_init(self) -> None:
        self._fe_cfg = FrontendConfig(depth_min=self.cfg.depth_min, depth_max=self.cfg.depth_max,
                                      sigma_geo_z2=self.cfg.tracking.frontend_sigma_geo_z2,
                                      photometric_weight=self.cfg.tracking.photometric_weight,
                                      sigma_col=self.cfg.tracking.icp_sigma_col,
                                      model_smoothing=self.cfg.tracking.frontend_model_smoothing,
                                      noisy_smoothing=self.cfg.tracking.frontend_noisy_smoothing,
                                      noisy_roughness=self.cfg.tracking.frontend_noisy_roughness,
                                      trust_z2_per_roughness=self.cfg.tracking.frontend_trust_z2_per_roughness,
                                      speckle_fill=self.cfg.tracking.frontend_speckle_fill)
        ds = self.cfg.tracking.frontend_downsample
        if ds == 0:  # auto: halve while the image stays at least AUTO_MIN_WIDTH wide
            ds = 1
            while self.k.width // (2 * ds) >= AUTO_MIN_WIDTH and ds < 4:
                ds *= 2
        self._fe_halvings = ds.bit_length() - 1  # 1 -> 0, 2 -> 1, 4 -> 2
        self._fe_k = self.k  # the front end's camera (halved with tracking.frontend_downsample; set at first use)
        self._fe_views: dict[int, KeyframeView] = {}  # keyframe index -> its sensor view (tracking thread only)
        self._fe_models: OrderedDict[int, ReferenceModel] = OrderedDict()  # built references, newest last (cache)
        self._fe_ref_idx = -1  # the current reference's keyframe index
        self._fe_state = "tracking"  # tracking | lost | confirming
        self._fe_confirmed = 0  # trusted frames since the relocalisation (confirming)
        self._fe_last_trusted = 0  # frame index of the last trusted, mapped pose
        self._fe_after_reloc = False  # the previous frame was relocalised after lost frames: the poses before it are
        # not in the map's frame, so the next guess takes _fe_reloc_step (or no motion) instead of their velocity
        self._fe_reloc_step: np.ndarray | None = None  # [4, 4] the camera's last step into the relocalised frame, as
        # its lost segment tracked it (None: unknown)
        self._fe_prev: tuple[int, np.ndarray, np.ndarray] | None = None  # the last frame tracked (index, depth, rgb)
        self._fe_noisy: set[int] = set()  # keyframes whose reference depth was smoothed as noisy
        self._fe_roughness = 0.0  # depth_roughness of the last reference built (1/m; 0: not measured)
        self._fe_speckled = False  # a reference's isolated holes were filled (logged once)
        self._fe_fill_live = False  # the last reference built was speckled: live frames' isolated holes are filled
        self._fe_segment: LostSegment | None = None  # lost frames tracked among themselves (tracking.lost_segment)
        self._fe_join: tuple[int, np.ndarray | None, list[int], list[int]] | None = None  # relocalised: (its frame,
        # its segment pose, the segment's earlier frames, their views), joined to the map when recovered (segment pose
        # None: mapping resumed on the segment's track, nothing moves)
        self.rejoined_frames = 0  # lost frames re-posed in the map's frame by a recovery (stats())
        self._fe_resumed: tuple[int, list[int]] | None = None  # mapping resumed on a lost segment's own track: (the
        # segment's first frame, the keyframe views from before it), tried for a re-anchoring (tracking.reanchor_every)
        self._fe_reanchor: tuple[int, np.ndarray, int] | None = None  # a correction [4, 4] found on a frame against
        # a keyframe, not yet confirmed: (frame, correction, keyframe)
        self._fe_reanchor_turn = 0  # the next keyframe from before the loss a re-anchoring try takes in turn
        self.reanchor_due: tuple[int, int, int, np.ndarray] | None = None  # a confirmed re-anchoring: (the first
        # frame to move, the frame relocalised, the keyframe it was relocalised against, its pose [4, 4] in that
        # keyframe's camera); SLAM.add_frame moves the poses, keyframes and Gaussians from the first frame on

    def _fe_frame(self, depth: np.ndarray, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The front end's copy of a frame ([H, W] metres, [H, W, 3] in [0, 1]): float64, halved
        ``tracking.frontend_downsample``'s power of two times."""
        if self._fe_halvings == 0:
            return np.asarray(depth, np.float64), np.asarray(rgb, np.float64)
        d, c, self._fe_k = downsample_frame(depth, rgb, self.k, self._fe_halvings, self._fe_cfg)
        return d, c

    def _fe_model(self, index: int) -> ReferenceModel:
        """The reference of keyframe ``index`` at its current pose (rebuilt when the back end moved it)."""
        with self._poses_lock:
            c2w = self.poses[index].copy()
        m = self._fe_models.get(index)
        if m is None or not np.allclose(m.c2w, c2w, atol=1e-9):
            v = self._fe_views[index]
            m = build_reference(v.depth, c2w, self._fe_k, self._fe_cfg, rgb=v.rgb, keyframe_id=index,
                                roughness=None if m is None else m.roughness)  # the same depth: measured once
            self._fe_models[index] = m
            self._fe_roughness = m.roughness
            self._fe_fill_live = m.speckle > self._fe_cfg.speckle_fill  # the camera's frames are speckled too
            if m.smoothing > self._fe_cfg.model_smoothing and index not in self._fe_noisy:
                if not self._fe_noisy:
                    log.info("keyframe %d: depth roughness %.4f > tracking.frontend_noisy_roughness %g: a noisy "
                             "camera; references are averaged over %d x %d pixels", index, m.roughness,
                             self._fe_cfg.noisy_roughness, m.smoothing, m.smoothing)
                self._fe_noisy.add(index)
            if m.speckle > self._fe_cfg.speckle_fill and not self._fe_speckled:
                log.info("keyframe %d: %.1f %% of its pixels are isolated holes (> tracking.frontend_speckle_fill %g): "
                         "they are filled from their neighbours in the references", index, 100 * m.speckle,
                         self._fe_cfg.speckle_fill)
                self._fe_speckled = True
        self._fe_models.move_to_end(index)
        while len(self._fe_models) > 6:
            self._fe_models.popitem(last=False)
        return m

    def _fe_add_keyframe(self, index: int, depth: np.ndarray, rgb: np.ndarray) -> None:
        """Make frame ``index`` (already posed) the reference for the next frames."""
        self._fe_views[index] = KeyframeView(index, depth, rgb, thumbnail(depth, rgb))
        self._fe_ref_idx = index
        self._fe_model(index)

    def _fe_candidates(self, live_thumb: np.ndarray) -> list[int]:
        """Keyframes to relocalise against: the best by thumbnail, plus the one nearest the last trusted pose."""
        n = self.cfg.tracking.relocalise_candidates
        ranked = sorted(self._fe_views, key=lambda i: thumbnail_distance(live_thumb, self._fe_views[i].thumb))
        with self._poses_lock:
            last = self.poses[self._fe_last_trusted][:3, 3].copy()
            near = min(self._fe_views, key=lambda i: float(np.linalg.norm(self.poses[i][:3, 3] - last)))
        out = ranked[:max(1, n - 1)]
        return out + ([near] if near not in out else ranked[n - 1:n])

    def _fe_retry(self, idx: int, live: LiveFrame, guess: np.ndarray, reason: str) -> TrackResult | None:
        """Frame ``idx`` tracked again when the reference lost it (a fast move), with twice the Gauss-Newton steps per
        level (a large step needs them at 320 x 240), from ``guess`` and then from the previous pose: against the
        frame before it (the nearest view; the reference may be several frames behind), or against the reference
        when that is the frame before. A previous frame that tracks it becomes the reference (unmapped, like a
        stale reference's replacement). Returns the trusted result, or None."""
        prev = self._fe_prev is not None and self._fe_prev[0] == idx - 1 and idx - 1 != self._fe_ref_idx
        with self._poses_lock:
            c2w = self.poses[idx - 1].copy()
        if prev:
            _, depth, rgb = self._fe_prev
            model = build_reference(depth, c2w, self._fe_k, self._fe_cfg, rgb=rgb, keyframe_id=idx - 1)
        else:
            model = self._fe_model(self._fe_ref_idx)
        wide = replace(self._fe_cfg, iters=tuple(2 * i for i in self._fe_cfg.iters))
        res = track(live, model, guess, wide)
        if not res.quality.trusted:
            res = track(live, model, c2w, wide)
            if not res.quality.trusted:
                return None
        if prev:
            log.info("frame %d: tracked against frame %d, the new reference (the keyframe of frame %d lost it: %s)",
                     idx, idx - 1, self._fe_ref_idx, reason)
            self._fe_views[idx - 1] = KeyframeView(idx - 1, depth, rgb, thumbnail(depth, rgb))
            self._fe_models[idx - 1] = model
            self._fe_ref_idx = idx - 1
            self._fe_used = (idx - 1, model.c2w)
        else:
            log.info("frame %d: tracked against the keyframe of frame %d with more steps (%s with fewer)", idx,
                     self._fe_ref_idx, reason)
        return res

    def _fe_check_anchor(self, idx: int, live: LiveFrame, depth: np.ndarray, rgb: np.ndarray, c2w: np.ndarray
                         ) -> None:
        """Frame ``idx``, tracked to ``c2w`` on a resumed track (``_fe_resumed``): every ``tracking.reanchor_every``
        frames, relocalise it against keyframes from before the loss: the best by thumbnail and the next of them in
        turn (a thumbnail compares depths, which a view from a metre away does not share), from guesses 50 cm out and
        with a 40 cm association gate on the coarsest level (a try is rare: it may look farther than a lost frame's).
        A relocalisation within ``REANCHOR_MIN`` of ``c2w`` ends the tries (the track was anchored well enough); a
        farther one is tried again on the next frame against the same keyframe, and when both give the same
        correction (``REANCHOR_AGREE``) it is due (``reanchor_due``: the pose it found, kept relative to that
        keyframe, which a mapping thread may still move)."""
        tc = self.cfg.tracking
        first, base = self._fe_resumed
        pending, self._fe_reanchor = self._fe_reanchor, None
        pending = pending if pending is not None and pending[0] == idx - 1 else None  # a confirmation is the next frame
        if pending is None and (idx - first) % tc.reanchor_every:
            return
        base = [i for i in base if i in self._fe_views]
        if not base:
            self._fe_resumed = None
            return
        if pending is not None:
            cands = [pending[2]] if pending[2] in base else []
        else:
            th = thumbnail(depth, rgb)
            best = min(base, key=lambda i: thumbnail_distance(th, self._fe_views[i].thumb))
            rest = [i for i in base if i != best]
            n = min(tc.relocalise_candidates - 1, len(rest))
            turn, self._fe_reanchor_turn = self._fe_reanchor_turn, self._fe_reanchor_turn + n
            cands = [best] + [rest[(turn + j) % len(rest)] for j in range(n)]
        if not cands:
            return
        fe = replace(self._fe_cfg, max_dist=self._fe_cfg.max_dist[:-1] + (REANCHOR_COARSE_GATE,))
        try:
            r = relocalise(live, [self._fe_model(i) for i in cands], fe, angles_deg=(10.0, 20.0),
                           shifts_m=(0.1, 0.25, 0.5))
        except RelocalisationError:
            return
        moved_m, moved_deg = pose_error(c2w, r.c2w)  # how far off the map the camera is on the resumed track
        if moved_m < REANCHOR_MIN[0] and moved_deg < REANCHOR_MIN[1]:
            log.info("frame %d: relocalised against the keyframe of frame %d within %.1f cm and %.1f deg of its "
                     "resumed track: the track is in the map's frame", idx, r.keyframe_id, 100 * moved_m, moved_deg)
            self._fe_resumed = None
            return
        corr = r.c2w @ np.linalg.inv(c2w)
        if pending is not None:
            apart_m, apart_deg = pose_error(pending[1] @ c2w, r.c2w)  # the two corrections, on this frame
            if apart_m <= REANCHOR_AGREE[0] and apart_deg <= REANCHOR_AGREE[1]:
                log.warning("frame %d: the track resumed at frame %d is %.0f cm and %.1f deg off the map, relocalised "
                            "twice against the keyframe of frame %d: every frame since moves into the map's frame",
                            idx, first, 100 * moved_m, moved_deg, r.keyframe_id)
                kf_c2w = self._fe_model(r.keyframe_id).c2w
                self.reanchor_due = (first, idx, r.keyframe_id, np.linalg.inv(kf_c2w) @ r.c2w)
                self._fe_resumed = None
                return
        self._fe_reanchor = (idx, corr, r.keyframe_id)  # confirmed (or not) on the next frame

    def _fe_segment_track(self, idx: int, live: LiveFrame, depth: np.ndarray, rgb: np.ndarray,
                          odom_guess: np.ndarray | None, first_guess: np.ndarray | None,
                          anchored: bool = False) -> np.ndarray:
        """Lost frame ``idx``'s pose in the lost segment (:class:`LostSegment`), tracked against the segment's
        reference from the odometry's guess, else constant velocity within the segment (then from the previous
        pose). The first lost frame starts a segment at ``first_guess`` (its tracking guess). A frame the segment does
        not track goes on the same segment at that guess, from itself as the new reference: the chain then holds to
        about one frame's motion, where a segment started afresh would keep its guessed frame for good. ``anchored``:
        the first frame's guess is trustworthy (:attr:`LostSegment.anchored`)."""
        fe = self._fe_cfg
        seg = self._fe_segment
        with self._poses_lock:
            prev = self.poses[-1].copy()
            prev2 = self.poses[-2].copy() if len(self.poses) >= 2 else prev
        if seg is None:  # the first lost frame (a segment is dropped whenever the camera is lost anew)
            start = first_guess if first_guess is not None else (odom_guess if odom_guess is not None else prev)
            self._fe_segment = LostSegment([idx], build_reference(depth, start, self._fe_k, fe, rgb=rgb,
                                                                   keyframe_id=idx,
                                                                   roughness=self._fe_roughness or None), [idx],
                                           anchored=anchored)
            return start
        guess = odom_guess if odom_guess is not None else \
            self._velocity_guess(prev2, prev) if len(seg.frames) >= 2 else prev
        res = track(live, seg.ref, guess, fe)
        if not res.quality.trusted and guess is not prev:
            res = track(live, seg.ref, prev, fe)
        seg.frames.append(idx)
        seg.trusted_run = seg.trusted_run + 1 if res.quality.trusted else 0
        if res.quality.trusted:
            pose = res.c2w
            if res.quality.coverage >= self.cfg.tracking.frontend_new_keyframe_coverage:
                return pose
        else:
            pose = guess
            log.info("frame %d: not tracked in the lost segment of frames %d..%d (%s); it goes on from the guess",
                     idx, seg.frames[0], idx - 1, res.quality.reason)
        seg.ref = build_reference(depth, pose, self._fe_k, fe, rgb=rgb, keyframe_id=idx, roughness=seg.ref.roughness)
        seg.views.append(idx)
        return pose

    def _fe_rejoin(self, idx: int) -> list[int]:
        """Frame ``idx`` recovered: move the lost segment that was relocalised (``_fe_join``) by the correction that
        puts its relocalised frame's segment pose on that frame's pose now (refined on the map, possibly).

        Returns:
            The segment's views (frames that became its reference), now in the map's frame; [] when nothing was
            joined.
        """
        join, self._fe_join = self._fe_join, None
        if join is None:
            return []
        at, seg_pose, frames, views = join
        if seg_pose is None:  # mapping resumed on the segment's own track: its frames keep their poses
            return views
        with self._poses_lock:
            corr = self.poses[at] @ np.linalg.inv(seg_pose)
            moved = 0.0
            for j in frames:
                new = corr @ self.poses[j]
                moved = max(moved, float(np.linalg.norm(new[:3, 3] - self.poses[j][:3, 3])))
                self.poses[j] = new
        self.rejoined_frames += len(frames)
        log.warning("frame %d: lost frames %d..%d (%d) re-posed in the map's frame (moved up to %.0f cm)", idx,
                    frames[0], frames[-1], len(frames), 100 * moved)
        return views

    def _track_keyframe(self, idx: int, rgb: np.ndarray, depth: np.ndarray, odom_guess: np.ndarray | None = None
                        ) -> tuple[np.ndarray, float, int, bool, str, float]:
        """Track frame ``idx`` ([H, W, 3] in [0, 1], [H, W] metres, both float64) from ``odom_guess`` (the last pose
        moved by the odometry since, :meth:`~semantic_gs_slam.slam.SLAM.odometry_guess`) when given, else from the
        constant-velocity guess.

        Returns:
            pose [4, 4], residual (m), correspondences, lost, pose source (tracking | lost | relocalised |
            confirming | recovered | resumed), coverage of the reference.
        """
        tc = self.cfg.tracking
        fe = self._fe_cfg
        with self._poses_lock:
            prev = self.poses[-1].copy()
            prev2 = self.poses[-2].copy() if len(self.poses) >= 2 else prev
        live = prepare_live(depth, self._fe_k, fe, rgb, fill_holes=self._fe_fill_live)
        res: TrackResult | None = None
        first_guess = None  # the first lost frame's tracking guess (where a lost segment starts)
        anchored = False  # ... and whether it is trustworthy (LostSegment.anchored)
        if self._fe_state != "lost":
            if odom_guess is not None:
                guess = odom_guess
            elif self._fe_after_reloc:  # the lost segment's last step, moved into the map with the frame
                step = self._fe_reloc_step
                guess = prev if step is None else self._velocity_guess(prev @ np.linalg.inv(step), prev)
            else:
                guess = self._velocity_guess(prev2, prev)
            model = self._fe_model(self._fe_ref_idx)
            self._fe_used = (model.keyframe_id, model.c2w)
            res = track(live, model, guess, fe)
            self._fe_after_reloc = False
            q = res.quality
            if q.trusted:
                if self._fe_state == "confirming":
                    self._fe_confirmed += 1
                    if self._fe_confirmed >= tc.relocalise_confirm:
                        self._fe_state = "tracking"
                        self._fe_prev = (idx, depth, rgb)
                        return res.c2w, q.residual, q.correspondences, False, "recovered", q.coverage
                    return res.c2w, q.residual, q.correspondences, False, "confirming", q.coverage
                self._fe_prev = (idx, depth, rgb)
                if self._fe_resumed is not None and tc.reanchor_every > 0:
                    self._fe_check_anchor(idx, live, depth, rgb, res.c2w)
                return res.c2w, q.residual, q.correspondences, False, "tracking", q.coverage
            if self._fe_state == "tracking":
                alt = self._fe_retry(idx, live, guess, q.reason)
                if alt is not None:
                    self._fe_prev = (idx, depth, rgb)
                    qa = alt.quality
                    return alt.c2w, qa.residual, qa.correspondences, False, "tracking", qa.coverage
            log.warning("frame %d: tracking lost against the keyframe of frame %d (%s)", idx, self._fe_ref_idx,
                        q.reason)
            if self._fe_state == "tracking":
                self._fe_lost_at = idx
            self._fe_state = "lost"
            self._fe_join = None  # a relocalisation not confirmed: its segment is not joined
            self._fe_segment = None
            first_guess = guess
            anchored = odom_guess is not None or self._steady_step()
        seg_pose = self._fe_segment_track(idx, live, depth, rgb, odom_guess, first_guess, anchored) \
            if tc.lost_segment else None
        tries = (idx - self._fe_lost_at) // tc.relocalise_every
        if (idx - self._fe_lost_at) % tc.relocalise_every == 0 and self._fe_views:
            cands = self._fe_candidates(thumbnail(depth, rgb))
            with self._poses_lock:
                last = self.poses[self._fe_last_trusted].copy()
            r = None
            # the first lost frame tries near guesses, then farther ones (a gap: the camera comes back 40 cm and 10
            # degrees from the nearest keyframe); later tries go straight to the farther ones
            for wide in ((False, True) if tries == 0 else (True,)):
                try:
                    r = relocalise(live, [self._fe_model(i) for i in cands], fe,
                                   extra_guesses=[last] if seg_pose is None else [last, seg_pose],
                                   angles_deg=(10.0, 20.0) if wide else (10.0,),
                                   shifts_m=(0.1, 0.25) if wide else (0.1,))
                    break
                except RelocalisationError as exc:
                    if wide:
                        log.warning("frame %d: relocalisation failed against frames %s: %s", idx, cands, exc)
            if r is not None and self._fe_resumed is not None and r.keyframe_id < self._fe_resumed[0]:
                # lost again, and taken back by a keyframe from before the resumed track: the camera is in the map's
                # frame again, the resumed track's frames are not (their correction is not this segment's)
                log.warning("frame %d: relocalised against the keyframe of frame %d, from before the track resumed at "
                            "frame %d: that track's frames %d..%d keep their anchor", idx, r.keyframe_id,
                            self._fe_resumed[0], self._fe_resumed[0], self._fe_lost_at - 1)
                self._fe_resumed = self._fe_reanchor = None
            if r is not None:
                self._fe_ref_idx = r.keyframe_id
                self._fe_used = (r.keyframe_id, self._fe_model(r.keyframe_id).c2w)
                # the first lost frame, relocalised at once, follows a trusted pose in the map: constant velocity
                # holds. After lost frames, the segment's step into this frame (both its poses in its frame) does
                self._fe_after_reloc = idx != self._fe_lost_at
                self._fe_reloc_step = np.linalg.inv(prev) @ seg_pose \
                    if seg_pose is not None and len(self._fe_segment.frames) > 1 else None
                self._fe_confirmed = 1
                q = r.quality
                if seg_pose is not None and len(self._fe_segment.frames) > 1:  # joined to the map once recovered
                    seg = self._fe_segment  # (SLAM.add_frame: _fe_rejoin)
                    self._fe_join = (idx, seg_pose, seg.frames[:-1], [v for v in seg.views if v != idx])
                self._fe_segment = None
                if self._fe_confirmed >= tc.relocalise_confirm:
                    self._fe_state = "tracking"
                    return r.c2w, q.residual, q.correspondences, False, "recovered", q.coverage
                self._fe_state = "confirming"
                log.warning("frame %d: relocalised against the keyframe of frame %d (coverage %.2f, agreement %.2f); "
                            "confirming", idx, r.keyframe_id, q.coverage, q.agreement)
                return r.c2w, q.residual, q.correspondences, False, "relocalised", q.coverage
        seg = self._fe_segment
        if seg_pose is not None and seg is not None and 0 < tc.lost_resume_after <= len(seg.frames) and \
                seg.anchored and seg.trusted_run >= tc.relocalise_confirm:
            # ground no keyframe saw: the map will not take the camera back until it returns; map on the segment's track
            self._fe_join = (idx, None, seg.frames[:-1], [v for v in seg.views if v != idx])
            if self._fe_resumed is None:  # (a second resume before a re-anchoring chains on the first one's track)
                self._fe_resumed = (seg.frames[0], sorted(i for i in self._fe_views if i < seg.frames[0]))
            self._fe_segment = None
            self._fe_state = "tracking"
            self._fe_prev = (idx, depth, rgb)
            log.warning("frame %d: lost since frame %d and not relocalised in the map for %d frames; mapping resumes "
                        "on the lost frames' own track, anchored at frame %d's guess (tracking.lost_resume_after)", idx,
                        seg.frames[0], len(seg.frames), seg.frames[0])
            return seg_pose, float("nan"), 0, False, "resumed", float("nan")
        q = res.quality if res is not None else None
        return (prev if seg_pose is None else seg_pose, float("nan") if q is None else q.residual,
                0 if q is None else q.correspondences, True, "lost",
                float("nan") if q is None else q.coverage)

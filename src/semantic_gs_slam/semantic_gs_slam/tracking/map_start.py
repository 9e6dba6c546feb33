"""Starting on a saved map (:meth:`~semantic_gs_slam.slam.SLAM.from_map`): a mixin of the engine.

A saved map (``params.npz``) keeps the Gaussians and the poses it was seen from (``view_c2w``, else the keyframes'
poses, else every frame's), but no images. The engine renders the map's depth and colour at those poses once, on the
first frame, at most ``MAX_START_WIDTH`` wide, and makes the renders it tries reference models of the front end
(:func:`~semantic_gs_slam.tracking.frontend.build_reference`).

Until a frame is relocalised against them, its pose is not trusted: it keeps the prior pose (where the saved run
ended), is reported ``lost`` and is not mapped. The first frame, then every ``tracking.relocalise_every``-th, is
relocalised like a lost frame of the keyframe front end (:func:`~semantic_gs_slam.tracking.frontend.relocalise`)
against the renders ranked best by a thumbnail of depth and intensity, plus the one nearest the prior, on images at
most ``MAX_START_WIDTH`` wide. The pose is refined by the render front end's ICP against the map at full size, and
must then track against the map on ``tracking.relocalise_confirm`` frames in a row, the relocalised one first,
before mapping starts (pose sources ``relocalised``, ``confirming``, ``recovered``). A confirming frame that fails
starts the relocalisation over. From then on the engine runs as usual, in the saved map's frame.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np

from semantic_gs_slam.config import Intrinsics
from semantic_gs_slam.tracking.frontend import (
    ReferenceModel,
    RelocalisationError,
    build_reference,
    prepare_live,
    relocalise,
)
from semantic_gs_slam.tracking.keyframe_tracking import thumbnail, thumbnail_distance

log = logging.getLogger("semantic_gs_slam")

#: metres; the front end's ``sigma_geo`` against the map's renders (its default, 1 cm, is a sensor's depth against
#: another's): a rendered surface is blurrier (RMS point-to-plane residual of a true pose on the kitchen map: 1.6 cm)
MAP_SIGMA_GEO = 0.015
#: relocalisation works on images at most this wide: the engine's, subsampled by a whole factor (a 1200x680 stream:
#: every 4th pixel of every 4th row), so the renders and the guesses cost the same at any camera size
MAX_START_WIDTH = 320
#: at most this many saved views are rendered as references (evenly spread over the saved ones): the start's cost
#: (one render each, on the first frame) stays bounded on a long map
MAX_START_VIEWS = 64


@dataclass
class MapStartView:
    """A view of the saved map rendered at one of its saved poses (caller's thread only)."""

    c2w: np.ndarray  # [4, 4] float64
    depth: np.ndarray  # [h, w] float32 metres (0: the map is not opaque there), the working camera's size
    rgb: np.ndarray  # [h, w, 3] float32 in [0, 1]
    thumb: np.ndarray  # [2, 15, 20] depth (m) and intensity (keyframe_tracking.thumbnail)
    model: ReferenceModel | None = None  # built when first tried (a 320x240 model is ~7 MB: not one per view)


class MapStart:
    """Relocalisation of the first frames in a saved map, then confirmation before mapping (a mixin)."""

    def _ms_init(self, views: list[np.ndarray], prior: np.ndarray) -> None:
        """Start relocalising against ``views`` ([4, 4] c2w of the saved map); ``prior``: the pose frames keep
        until they are relocalised (where the saved run ended)."""
        if len(views) > MAX_START_VIEWS:
            pick = np.linspace(0, len(views) - 1, MAX_START_VIEWS).round().astype(int)
            views = [views[i] for i in pick]
        self.start_views = [np.asarray(v, np.float64) for v in views]  # the saved map's poses (kept in save())
        self._ms_prior = np.asarray(prior, np.float64)
        self._ms_refs: list[MapStartView] | None = None  # rendered on the first frame
        self._ms_fe = replace(self._fe_cfg, sigma_geo=MAP_SIGMA_GEO)  # the front end's settings against the renders
        self._ms_state = "relocalising"  # relocalising | confirming | done
        self._ms_confirmed = 0
        self._ms_lost = 0  # frames not relocalised since the last try began (relocalise_every)
        f = max(1, math.ceil(self.k.width / MAX_START_WIDTH))
        self._ms_step = f  # the working camera takes every f-th pixel of every f-th row
        self._ms_k = self.k if f == 1 else Intrinsics(-(-self.k.width // f), -(-self.k.height // f), self.k.fx / f,
                                                      self.k.fy / f, self.k.cx / f, self.k.cy / f)

    @property
    def localised(self) -> bool:
        """Whether the engine's frames are trusted in the map's frame: always for a fresh map; after
        :meth:`~semantic_gs_slam.slam.SLAM.from_map`, once a frame was relocalised and confirmed (mapping runs)."""
        return getattr(self, "_ms_state", "done") == "done"

    def _ms_references(self) -> list[MapStartView]:
        """The saved map rendered at each saved view (once): depth normalised by the silhouette where it is at
        least ``tracking.min_silhouette``, and colour."""
        if self._ms_refs is None:
            refs = []
            for c2w in self.start_views:
                out = self.render_view(c2w, semantic=False, k=self._ms_k)
                sil = out.silhouette
                d = (out.depth / sil.clamp_min(1e-6)) * (sil > self.cfg.tracking.min_silhouette)
                depth = d.cpu().numpy().astype(np.float64)
                rgb = (out.rgb / sil.clamp_min(1e-6)[..., None]).clamp(0, 1).cpu().numpy().astype(np.float64)
                rgb = rgb * (depth > 0)[..., None]
                if (depth > 0).mean() < 0.05:  # the map hardly covers this view (pruned, or a pose off the map)
                    continue
                refs.append(MapStartView(c2w, depth.astype(np.float32), rgb.astype(np.float32), thumbnail(depth, rgb)))
            self._ms_refs = refs
            log.info("start on a saved map: %d of its %d views rendered as references", len(refs),
                     len(self.start_views))
        return self._ms_refs

    def _ms_model(self, i: int) -> ReferenceModel:
        """The reference model of render ``i`` (built once; at most 8 kept)."""
        v = self._ms_refs[i]
        if v.model is None:
            built = [r for r in self._ms_refs if r.model is not None]
            if len(built) >= 8:
                built[0].model = None
            v.model = build_reference(v.depth.astype(np.float64), v.c2w, self._ms_k, self._ms_fe,
                                      rgb=v.rgb.astype(np.float64), keyframe_id=i)
        return v.model

    def _ms_track(self, idx: int, rgb_t, depth_t, rgb: np.ndarray, depth: np.ndarray
                  ) -> tuple[np.ndarray, float, int, bool, str, float]:
        """Frame ``idx`` while the start is not confirmed ([H, W, 3] in [0, 1], [H, W] metres, float64; and the
        same as tensors for the map tracking).

        Returns:
            pose [4, 4], residual (m), correspondences, lost, pose source (lost | relocalised | confirming |
            recovered), coverage.
        """
        tc = self.cfg.tracking
        if self._ms_state == "confirming":
            with self._poses_lock:
                prev = self.poses[-1].copy()
                prev2 = self.poses[-2].copy() if self._ms_confirmed >= 2 else prev  # velocity once two are trusted
            c2w, residual, inliers, failed, _ = self._track(rgb_t, depth_t, None,
                                                            guess=self._velocity_guess(prev2, prev))
            if not failed:
                self._ms_confirmed += 1
                if self._ms_confirmed >= tc.relocalise_confirm:
                    self._ms_done(idx)
                    return c2w, residual, inliers, False, "recovered", float("nan")
                return c2w, residual, inliers, False, "confirming", float("nan")
            log.warning("frame %d: the pose relocalised in the saved map did not track; relocalising again", idx)
            self._ms_state = "relocalising"
            self._ms_lost = 0
        self._ms_lost += 1
        if (self._ms_lost - 1) % tc.relocalise_every:  # between tries: lost at once
            return self._ms_prior.copy(), float("nan"), 0, True, "lost", float("nan")
        refs = self._ms_references()
        if not refs:
            log.warning("frame %d: the saved map renders nothing at its saved views; cannot relocalise", idx)
            return self._ms_prior.copy(), float("nan"), 0, True, "lost", float("nan")
        f = self._ms_step
        depth, rgb = np.ascontiguousarray(depth[::f, ::f]), np.ascontiguousarray(rgb[::f, ::f])
        live = prepare_live(depth, self._ms_k, self._ms_fe, rgb)
        n = max(3, tc.relocalise_candidates)
        th = thumbnail(depth, rgb)
        ranked = sorted(range(len(refs)), key=lambda i: thumbnail_distance(th, refs[i].thumb))
        near = min(range(len(refs)), key=lambda i: float(np.linalg.norm(refs[i].c2w[:3, 3] - self._ms_prior[:3, 3])))
        cands = ranked[:n] + ([near] if near not in ranked[:n] else [])
        try:
            r = relocalise(live, [self._ms_model(i) for i in cands], self._ms_fe, extra_guesses=[self._ms_prior],
                           angles_deg=(10.0, 20.0), shifts_m=(0.1, 0.25))
        except RelocalisationError as exc:
            log.warning("frame %d: not relocalised in the saved map yet (%s); not mapped", idx, exc)
            return self._ms_prior.copy(), float("nan"), 0, True, "lost", float("nan")
        # refined against the map as the render front end tracks (its sharper render, its lost test)
        c2w, residual, inliers, failed, _ = self._track(rgb_t, depth_t, None, guess=r.c2w,
                                                        on_failure="checking the relocalised pose on the map")
        if failed:
            log.warning("frame %d: relocalised against the saved map's view %d, but the map does not confirm it; "
                        "not mapped", idx, r.keyframe_id)
            return self._ms_prior.copy(), float("nan"), 0, True, "lost", float("nan")
        self._ms_confirmed = 1
        if tc.relocalise_confirm <= 1:
            self._ms_done(idx)
            return c2w, residual, inliers, False, "recovered", r.quality.coverage
        self._ms_state = "confirming"
        log.warning("frame %d: relocalised in the saved map against its view %d; confirming", idx, r.keyframe_id)
        return c2w, residual, inliers, False, "relocalised", r.quality.coverage

    def _ms_done(self, idx: int) -> None:
        self._ms_state = "done"
        self._ms_refs = None  # the renders are not needed any more
        log.warning("frame %d: the start in the saved map is confirmed; mapping in its frame", idx)

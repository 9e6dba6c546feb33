"""Fill numba's on-disk cache once: every compiled CPU kernel of the SLAM engine and the object database.

``scripts/setup.sh`` runs this when a kernel module has no cache yet (a fresh clone). Without it the first processes
of ``make test`` (two pytest workers, the SLAM servers they start) would each compile the same kernels at the same
time (about 16 s of CPU each on this project's CI machine) before one of them has written the cache. Here they are
compiled once, by a tiny SLAM run on a synthetic home with each tracking front end; later processes load them.

Prints one line: how many kernels were compiled and how many were already cached.
"""

from __future__ import annotations

import logging
import os
import sys
import tempfile
import time


def main() -> int:
    try:
        import numba  # noqa: F401
    except ImportError:
        print("numba is not installed: nothing to compile")
        return 0
    import numpy as np

    from object_query.kernels import bin_sums
    from semantic_gs_slam import SLAM, SlamConfig, load_dataset
    from semantic_gs_slam.config import MappingConfig, TrackingConfig
    from semantic_gs_slam.synthetic.scenes import generate

    logging.getLogger("semantic_gs_slam").setLevel(logging.ERROR)  # two rough maps: tracking may be lost, fine here
    t0 = time.monotonic()
    bin_sums(np.zeros(4, np.int64), np.zeros((4, 3), np.float32), 2, fast=True)
    with tempfile.TemporaryDirectory() as tmp:
        generate(os.path.join(tmp, "home"), frames=3, width=96, height=54)
        ds = load_dataset(os.path.join(tmp, "home"))
        for frontend in ("render", "keyframe"):
            eng = SLAM(SlamConfig(intrinsics=ds.intrinsics, tracking=TrackingConfig(frontend=frontend),
                                  mapping=MappingConfig(first_frame_iters=2, iters=1, keyframe_every=1)), ds.classes)
            for i in range(len(ds)):
                f = ds[i]
                eng.add_frame(f.rgb, f.depth, f.semantics, f.timestamp)
        # what the tiny run above does not reach: a camera frame halved for the front end (640x480 and up), and
        # uint8 colour as a ROS image brings it
        from semantic_gs_slam.config import Intrinsics
        from semantic_gs_slam.io.host_frame import host_frame
        from semantic_gs_slam.tracking.frontend import FrontendConfig, downsample_frame

        f = ds[0]
        rgb8 = (f.rgb * 255).astype(np.uint8)
        host_frame(rgb8, f.depth, 0.1, 10.0)
        k = Intrinsics(f.depth.shape[1], f.depth.shape[0], 50.0, 50.0, 48.0, 27.0)
        downsample_frame(*host_frame(rgb8, f.depth, 0.1, 10.0)[::-1], k, 1, FrontendConfig())
    from numba.core.registry import CPUDispatcher

    kernels = {id(v): v for m in list(sys.modules.values()) for v in list(getattr(m, "__dict__", {}).values())
               if isinstance(v, CPUDispatcher)}
    from object_query.kernels import _compiled

    kernels[id(_compiled())] = _compiled()
    compiled = sum(len(k.stats.cache_misses) for k in kernels.values())
    cached = sum(len(k.stats.cache_hits) for k in kernels.values())
    print(f"numba cache: {compiled} kernels compiled, {cached} already cached ({time.monotonic() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

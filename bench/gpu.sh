#!/usr/bin/env bash
# One command that proves the SLAM engine on a CUDA GPU, all in one run (< 10 minutes on
# an H100): installs gsplat from carried wheels, builds its CUDA code (torch's JIT loader), runs the
# GPU agreement tests, prints the quality / speed table at 300x170, 600x340 and 1200x680 (frame 0
# separately, peak GPU memory; 1200x680 again with the CPU's settings as the baseline, config.DEVICE_DEFAULTS)
# and the streaming-at-30-Hz figures. Paste the table into docs/figures.md ("SLAM on a GPU").
#
#   bash bench/gpu.sh --download    # where a package index is reachable: fetch the wheels into .whl/
#   bash bench/gpu.sh               # on the CUDA machine (no network needed): everything
#   bash bench/gpu.sh --setup-only  # install + build gsplat only (what `make setup-gpu` runs)
#
# Environment: PYTHON (default python3: a CUDA torch must be importable), WHEELS (default .whl),
# GPU_SITE (where the wheels are installed, default .gpu-site; put on PYTHONPATH), OUT (where the
# table is written, default out/gpu), DATA (generated sequences, default /tmp/slam_gpu_data),
# FRAMES (per size, default 60), SIZES (default "300x170 600x340 1200x680"), TORCH_CUDA_ARCH_LIST
# and FAST_COMPILE (gsplat's build flags: as set, the same that any later run must see), MAX_JOBS.
# REAL_DATA (a real RGB-D sequence folder, e.g. 7-Scenes; default none): after the table, bench/slam_real.py on
# CUDA: first the real-camera target (640x480, every frame of REAL_TARGET_FRAMES (default 250) from REAL_TARGET_START
# (default 250), realtime profile, 30-s refinement: FPS >= 30), then three times (the defaults with a 900-iteration
# refinement with poses; every pixel seeded on keyframes with the same refinement; geometry labels), REAL_FRAMES
# (default 250) every REAL_STRIDE-th frame (default 2; 1 for a copy of every 2nd frame, which is what fits beside the
# wheels on a device machine). Run nothing else on the
# machine meanwhile: a busy host slows the GPU loop (its frames are paced by one host thread).
set -euo pipefail
if [ -n "${REAL_DATA:-}" ]; then  # relative to the caller's folder: checked and made absolute before the cd below
  [ -d "$REAL_DATA" ] || { printf '\033[1;31m[gpu]\033[0m REAL_DATA=%s is not a folder (a real RGB-D sequence: 7-Scenes, TUM RGB-D, Replica layout)\n' "$REAL_DATA" >&2; exit 2; }
  REAL_DATA=$(cd "$REAL_DATA" && pwd)
fi
cd "$(dirname "$0")/.."
ROOT=$PWD
PY=${PYTHON:-python3}
WHEELS=${WHEELS:-.whl}
SITE=${GPU_SITE:-$ROOT/.gpu-site}
OUT_DIR=${OUT:-$ROOT/out/gpu}
FRAMES=${FRAMES:-60}
SIZES=${SIZES:-300x170 600x340 1200x680}
# pinned like requirements/*.in; the GPU machine's Python may differ from ours (GPU_PYTHON_VERSION)
GPU_WHEELS=(gsplat==1.5.3 jaxtyping==0.3.11 wadler-lindig==0.1.8 rich==15.0.0 markdown-it-py==4.3.0
  mdurl==0.1.2 pygments==2.21.0 ninja==1.13.2 pillow==13.0.0 pyyaml==6.0.3 pytest==9.2.0 pluggy==1.7.0
  iniconfig==2.3.1 packaging==26.3 pytest-timeout==2.4.0)
T0=$(date +%s)

log() { printf '\033[1;34m[gpu %4ds]\033[0m %s\n' "$(( $(date +%s) - T0 ))" "$*" >&2; }
die() { printf '\033[1;31m[gpu]\033[0m %s\n' "$*" >&2; exit 2; }

if [ "${1:-}" = --download ]; then
  ver=${GPU_PYTHON_VERSION:-3.12}
  log "downloading ${#GPU_WHEELS[@]} wheels for Python $ver into $WHEELS"
  "$PY" -m pip download -q --no-deps -d "$WHEELS" --python-version "$ver" --only-binary=:all: \
    --platform manylinux2014_x86_64 --platform manylinux_2_28_x86_64 "${GPU_WHEELS[@]}"
  ls -1 "$WHEELS" >&2
  exit 0
fi

# --- 1. a CUDA torch and nvcc ------------------------------------------------------------------
"$PY" -c 'import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)' 2>/dev/null \
  || die "$PY has no CUDA torch or sees no GPU (torch: $("$PY" -c 'import torch; print(torch.__version__)' 2>&1 | tail -1)); this command needs a CUDA machine"
if ! command -v nvcc >/dev/null; then
  for d in "${CUDA_HOME:-}" /usr/local/cuda; do
    if [ -n "$d" ] && [ -x "$d/bin/nvcc" ]; then export CUDA_HOME=$d PATH="$d/bin:$PATH"; break; fi
  done
fi
command -v nvcc >/dev/null || die "nvcc not found (set CUDA_HOME): gsplat compiles its CUDA code on first use; see docs/slam.md"
log "GPU: $("$PY" -c 'import torch; print(torch.cuda.get_device_name(0), "| torch", torch.__version__, "| CUDA", torch.version.cuda)'); nvcc: $(nvcc --version | tail -1)"

# --- 2. gsplat and the test tools from the carried wheels --------------------------------------
missing=()
for mod in gsplat jaxtyping rich PIL yaml pytest pytest_timeout; do
  PYTHONPATH="$SITE${PYTHONPATH:+:$PYTHONPATH}" "$PY" -c "import $mod" 2>/dev/null || missing+=("$mod")
done
if [ ${#missing[@]} -gt 0 ]; then
  ls "$WHEELS"/gsplat-1.5.3-*.whl >/dev/null 2>&1 \
    || die "missing ${missing[*]} and no wheels in $WHEELS: run 'bash bench/gpu.sh --download' where an index is reachable and bring $WHEELS along"
  log "installing ${#GPU_WHEELS[@]} wheels from $WHEELS into $SITE (missing here: ${missing[*]})"
  "$PY" -m pip install -q --no-index --no-deps --upgrade --target "$SITE" "$WHEELS"/*.whl
fi
export PYTHONPATH="$SITE:$ROOT/src/semantic_gs_slam:$ROOT/src/semantic_gs_slam_ros:$ROOT/src/object_query${PYTHONPATH:+:$PYTHONPATH}"
export PATH="$SITE/bin:$PATH"  # the ninja build tool

# --- 3. gsplat's CUDA extension (JIT build, cached under ~/.cache/torch_extensions) --------------
# The build flags (FAST_COMPILE, NO_FAST_MATH, TORCH_CUDA_ARCH_LIST) are left as the environment has them:
# torch's JIT loader rebuilds the whole extension in any later process whose flags differ, so a build made
# here with other flags than a plain run's would cost that run ~85 s at its first frame (and FAST_COMPILE=1
# builds at -O0). MAX_JOBS only sets the parallelism.
nproc=$(nproc)
export MAX_JOBS=${MAX_JOBS:-$(( nproc > 2 ? nproc - 2 : 1 ))}
log "building gsplat's CUDA code (arch ${TORCH_CUDA_ARCH_LIST:-default: this GPU}, FAST_COMPILE=${FAST_COMPILE:-0}, MAX_JOBS=$MAX_JOBS; ~85 s the first time)"
t=$(date +%s)
"$PY" -c 'import sys; from gsplat.cuda._backend import _C; sys.exit(0 if _C is not None else 1)' \
  || die "gsplat's CUDA build failed (see above; nvcc must support this GPU's arch and match torch's CUDA major)"
log "gsplat ready in $(( $(date +%s) - t )) s"
[ "${1:-}" = --setup-only ] && { log "setup done: export PYTHONPATH=$SITE:\$PYTHONPATH to use it"; exit 0; }

# --- 4. agreement tests on the GPU ---------------------------------------------------------------
mkdir -p "$OUT_DIR"
log "GPU agreement tests"
set +e  # a failing test must not skip the table: its exit code is returned at the end
"$PY" -m pytest -q -p no:cacheprovider -o addopts="" --import-mode=importlib \
  --rootdir=src/semantic_gs_slam/test --confcutdir=src/semantic_gs_slam/test \
  src/semantic_gs_slam/test/test_gsplat_gpu.py src/semantic_gs_slam/test/test_gsplat_conventions.py \
  src/semantic_gs_slam/test/test_renderer.py src/semantic_gs_slam/test/test_device.py \
  src/semantic_gs_slam/test/test_tracking.py 2>&1 | tee "$OUT_DIR/tests.txt"
tests_rc=${PIPESTATUS[0]}
set -e

# --- 5. quality / speed table and streaming at 30 Hz ----------------------------------------------
log "quality / speed table ($SIZES, $FRAMES frames each) and streaming"
# shellcheck disable=SC2086
"$PY" bench/slam_gpu.py --device cuda --backend gsplat --frames "$FRAMES" --sizes $SIZES \
  --threads "$(( nproc < 8 ? nproc : 8 ))" --workers "$nproc" --data "${DATA:-/tmp/slam_gpu_data}" --baseline \
  | tee "$OUT_DIR/table.md"

# --- 6. a real sequence on CUDA, when REAL_DATA names one ---------------------
if [ -n "${REAL_DATA:-}" ]; then
  real=("$PY" bench/slam_real.py "$REAL_DATA" --frames "${REAL_FRAMES:-250}" --stride "${REAL_STRIDE:-2}"
        --device cuda --no-open3d --quiet --curve-every 125 --profile default)
  echo '{"mapping": {"keyframe_pixel_stride": 1}}' > "$OUT_DIR/kps1.json"
  set +e  # one failing run must not hide the others; their exit codes are reported at the end
  # the real-camera target on a GPU: 640x480, every frame, the realtime profile (30-s refinement), >= 30 FPS; frames
  # REAL_TARGET_START.. (default 250: the half held out from the front end's tuning), REAL_TARGET_FRAMES of them
  log "real sequence $REAL_DATA: the GPU target (640x480, every frame, realtime profile)"
  "$PY" bench/slam_real.py "$REAL_DATA" --size 640x480 --stride 1 --start "${REAL_TARGET_START:-250}" \
    --frames "${REAL_TARGET_FRAMES:-250}" --device cuda --no-open3d --quiet --eval-every 10 --curve-every 50 \
    --profile realtime --threads "$(( nproc < 8 ? nproc : 8 ))" | tee "$OUT_DIR/real_target.md"
  target_rc=${PIPESTATUS[0]}
  log "real sequence $REAL_DATA: defaults, then a 900-iteration refinement with poses"
  "${real[@]}" --refine-iters 900 --refine-poses | tee "$OUT_DIR/real.md"
  real_rc="$target_rc ${PIPESTATUS[0]}"
  log "the same with every pixel seeded on keyframes (mapping.keyframe_pixel_stride 1)"
  "${real[@]}" --config "$OUT_DIR/kps1.json" --refine-iters 900 --refine-poses | tee "$OUT_DIR/real_kps1.md"
  real_rc="$real_rc ${PIPESTATUS[0]}"
  log "geometry labels"
  "${real[@]}" --labels geometry | tee "$OUT_DIR/real_labels.md"
  real_rc="$real_rc ${PIPESTATUS[0]}"
  set -e
  log "real-sequence runs exit $real_rc"
  [ "$real_rc" = "0 0 0 0" ] || { [ "$tests_rc" -ne 0 ] || tests_rc=1; }
fi
log "done in $(( $(date +%s) - T0 )) s; tests exit $tests_rc; table in $OUT_DIR/table.md (paste into docs/figures.md)"
exit "$tests_rc"

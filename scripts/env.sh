# scripts/env.sh — `source scripts/env.sh` gives a shell with the virtualenv and the built
# workspace active, in both worlds (ROS 2 wheels from PyPI, or a system ROS 2 that setup used).
# bash only. Optional: VENV, ROS_DOMAIN_ID (default 0). `--no-workspace` skips install/.
#
# Always: ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST — DDS discovery stays on loopback.

_hr_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
_hr_venv="${VENV:-$_hr_root/.venv}"
_hr_ws=1; [ "${1:-}" = "--no-workspace" ] && _hr_ws=
case $- in *u*) _hr_nu=1; set +u ;; *) _hr_nu= ;; esac   # venv/colcon scripts are not set -u safe
_hr_pre() { local c="${!1:-}"; case ":$c:" in *":$2:"*) ;; *) export "$1=$2${c:+:$c}" ;; esac; }

export HOME_ROBOT_ROOT="$_hr_root"
if [ ! -x "$_hr_venv/bin/python" ]; then
  echo "env.sh: no virtualenv at $_hr_venv — run 'make setup' first" >&2
else
  _hr_world="$(cat "$_hr_venv/home_robot_world" 2>/dev/null || echo wheels)"
  # shellcheck disable=SC1091
  . "$_hr_venv/bin/activate"
  if [ "$_hr_world" = wheels ]; then
    _hr_pre AMENT_PREFIX_PATH "$_hr_venv"; _hr_pre CMAKE_PREFIX_PATH "$_hr_venv"
    # Do once what the wheels' ros_wheels_bootstrapper .pth re-exec does at every Python start
    # (it costs ~35 ms per process and builds LD_LIBRARY_PATH in random order).
    for _hr_d in "$_hr_venv"/lib/python3*/site-packages/ros_*.libs "$_hr_venv/lib"; do
      [ -d "$_hr_d" ] && _hr_pre LD_LIBRARY_PATH "$_hr_d"
    done
    export _ROS_WHEELS_BOOTSTRAP_COMPLETE=1 RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
  elif [ -z "${ROS_DISTRO:-}" ]; then
    _hr_ros="$(cat "$_hr_venv/home_robot_ros_setup" 2>/dev/null || true)"
    if [ -n "$_hr_ros" ] && [ -f "$_hr_ros" ]; then
      # shellcheck disable=SC1090
      . "$_hr_ros"
    else
      echo "env.sh: this workspace was built against a system ROS 2; source /opt/ros/<distro>/setup.bash first" >&2
    fi
  fi
  if [ -n "$_hr_ws" ] && [ -f "$_hr_root/install/local_setup.bash" ]; then
    # shellcheck disable=SC1091
    . "$_hr_root/install/local_setup.bash"
  elif [ -n "$_hr_ws" ]; then
    echo "env.sh: workspace not built yet — run 'make setup'" >&2
  fi
  LD_LIBRARY_PATH="${LD_LIBRARY_PATH%:}"; export LD_LIBRARY_PATH   # colcon leaves a trailing ':'
fi
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
# Fast DDS profile: a 2 s participant lease, so a killed node leaves the graph in 2 s, not 20 s
# (the decision maker then fails the goal it waits on at once). A profile of your own wins.
if [ -z "${FASTRTPS_DEFAULT_PROFILES_FILE:-}${FASTDDS_DEFAULT_PROFILES_FILE:-}" ]; then
  export FASTRTPS_DEFAULT_PROFILES_FILE="$_hr_root/src/home_robot_bringup/config/dds/fastdds_liveliness.xml"
  export FASTDDS_DEFAULT_PROFILES_FILE="$FASTRTPS_DEFAULT_PROFILES_FILE"
fi
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-0}"
export PYTHONUNBUFFERED=1
# OpenMP workers (torch's CPU kernels) spin briefly, then sleep, while they wait (libgomp's default spins 15 times
# longer): on a robot's few cores the tracking thread, the mapping thread and the other nodes share them. 2 cores,
# kitchen frames 0-249: `realtime` 46 -> 72 FPS, the default profile unchanged (3.9 FPS). `make test` sets 0 (its
# three workers share two cores). A value of your own wins.
export GOMP_SPINCOUNT="${GOMP_SPINCOUNT:-20000}"

# No ros2 CLI in the wheel world: `ros_exe PKG EXE` prints an installed entry point,
# `ros_run PKG EXE ARGS...` runs it (same layout `ros2 run` uses: <prefix>/lib/<pkg>/<exe>).
ros_exe() { local p IFS=:; for p in $AMENT_PREFIX_PATH; do
  if [ -x "$p/lib/$1/$2" ]; then echo "$p/lib/$1/$2"; return 0; fi; done
  echo "ros_exe: $1/$2 not found (is the workspace built and sourced?)" >&2; return 127; }
ros_run() { local e; e="$(ros_exe "$1" "$2")" || return 127; shift 2; "$e" "$@"; }

if [ -z "${HOME_ROBOT_ENV_QUIET:-}" ] && [ -x "$_hr_venv/bin/python" ]; then
  echo "home-robot env: ${_hr_world} world, ROS_DOMAIN_ID=$ROS_DOMAIN_ID, discovery LOCALHOST; ros_run PKG EXE to run a node"
fi
[ -n "$_hr_nu" ] && set -u
unset _hr_root _hr_venv _hr_ws _hr_nu _hr_world _hr_d _hr_ros
true

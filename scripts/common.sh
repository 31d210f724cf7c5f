#!/usr/bin/env bash
# Shared by run.sh and test.sh: install what is missing (Debian packages only), then
# configure and build the catkin package in ./build. Idempotent: quick when all is there.
set -eo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BUILD="${NEEDLE_SIM_BUILD_DIR:-$ROOT/build}"
# The devel space sits beside ./build, not inside it: rosrun skips everything under
# <package>/build/, so a devel space there hides the node and the tool from it.
DEVEL="${NEEDLE_SIM_DEVEL_DIR:-$ROOT/devel}"

# What the core library, the needle_sim tool and their tests need (NEEDLE_SIM_ROS=OFF).
CORE_PACKAGES=(cmake g++ libeigen3-dev libsuitesparse-dev libopenblas0-pthread libyaml-cpp-dev nlohmann-json3-dev
  libcli11-dev libassimp-dev libnlopt-dev libgtest-dev)
# Everything the package needs from Debian (package.xml declares the same dependencies).
PACKAGES=(
  "${CORE_PACKAGES[@]}"
  # build tools and ROS 1 from Debian (Debian's own ROS 1 packages: there is no /opt/ros)
  catkin ros-core-dev rosbash libroscpp-dev ros-std-msgs ros-geometry-msgs
  ros-sensor-msgs ros-nav-msgs ros-std-srvs ros-visualization-msgs ros-trajectory-msgs libtrajectory-msgs-dev
  libdiagnostic-updater-dev libtf2-ros-dev libactionlib-dev libactionlib-msgs-dev ros-actionlib-msgs
  libdynamic-reconfigure-config-init-mutex-dev
  libnodeletlib-dev libnodeletlib-tools pluginlib-dev librosbag-storage-dev libroslib-dev
  # what a Python client of the node imports (messages, services, the action, tf, reconfigure)
  python3-rosbag python3-rospy python3-geometry-msgs python3-nav-msgs python3-sensor-msgs python3-visualization-msgs
  python3-diagnostic-msgs python3-std-srvs python3-tf2-msgs python3-tf2-ros python3-trajectory-msgs
  python3-actionlib python3-actionlib-msgs python3-dynamic-reconfigure
  # the viewer, and its test under a virtual display
  rviz xvfb python3-pil
  python3-rostest librostest-dev
  # plots
  python3-matplotlib python3-yaml
  # needle_sim ensemble: sampling and statistics, the Dask engine (the tests use psutil)
  python3-numpy python3-scipy python3-dask python3-distributed python3-psutil
)

install_missing() {
  local missing=()
  for p in "${PACKAGES[@]}"; do
    if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
      missing+=("$p")
    fi
  done
  if ((${#missing[@]})); then
    echo "needle_sim: installing missing packages: ${missing[*]}" >&2
    local SUDO=""
    if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
    export DEBIAN_FRONTEND=noninteractive
    $SUDO apt-get update -q >&2
    $SUDO apt-get install -y -q --no-install-recommends "${missing[@]}" >&2
  fi
}

# The scripts' builds compile each target's sources eight to a unit (CMake's unity build):
# about 40 % less compile time on two cores (doc/benchmarks.md, "Sanitizers, fuzzing, CI"),
# the same objects' code (a run's results bit for bit). A catkin workspace build
# (scripts/workspace_check.sh, a user's) compiles them one by one, which keeps every source
# compiling on its own includes.
UNITY=(-DCMAKE_UNITY_BUILD=ON)

build() {
  # A pyenv python3 first on PATH breaks catkin: always name Debian's interpreter.
  if [ ! -f "$BUILD/CMakeCache.txt" ] || ! grep -q "^CATKIN_DEVEL_PREFIX:PATH=$DEVEL\$" "$BUILD/CMakeCache.txt"; then
    cmake -S "$ROOT" -B "$BUILD" -DCMAKE_BUILD_TYPE=Release "${UNITY[@]}" \
      -DCATKIN_DEVEL_PREFIX="$DEVEL" \
      -DPYTHON_EXECUTABLE=/usr/bin/python3 -DPython3_EXECUTABLE=/usr/bin/python3 >&2
  fi
  cmake --build "$BUILD" -j"$(nproc)" >&2
  # catkin puts the devel space's Python path (generated message modules) into its
  # environment only if it exists at configure time: configure once more after the first
  # build, so that devel/setup.bash and the rostests see needle_sim.msg.
  if grep -q "^export PYTHONPATH=''" "$BUILD/catkin_generated/setup_cached.sh" 2>/dev/null; then
    cmake "$BUILD" >&2
  fi
  cmake --build "$BUILD" -j"$(nproc)" --target tests >&2
}

# Only the package's generated messages, services, action and reconfigure header in the
# regular build's devel space (what test/tsan_ros compiles against).
build_generated() {
  if [ ! -f "$BUILD/CMakeCache.txt" ]; then
    cmake -S "$ROOT" -B "$BUILD" -DCMAKE_BUILD_TYPE=Release "${UNITY[@]}" -DCATKIN_DEVEL_PREFIX="$DEVEL" \
      -DPYTHON_EXECUTABLE=/usr/bin/python3 -DPython3_EXECUTABLE=/usr/bin/python3 >&2
  fi
  cmake --build "$BUILD" -j"$(nproc)" --target needle_sim_generate_messages_cpp needle_sim_gencfg >&2
}

# The hardening build shared by sanitize.sh and fuzz.sh (issue #8): clang, which compiles this
# code about 2.5 times faster than g++ under the sanitizers, ASan + UBSan on everything, the
# libFuzzer targets beside the unit tests. A folder configured otherwise (an older g++ ASan
# build) is made anew: a compiler cannot change in a CMake build folder.
# Under ./build, which rosrun does not search: a sanitized tool beside the devel space's
# would make `rosrun needle_sim needle_sim` ambiguous.
SANITIZED_BUILD="${NEEDLE_SIM_ASAN_DIR:-$ROOT/build/asan}"
configure_sanitized() {
  PACKAGES+=(clang libclang-rt-14-dev)
  install_missing
  if [ -f "$SANITIZED_BUILD/CMakeCache.txt" ] && ! grep -q "^NEEDLE_SIM_FUZZ:BOOL=ON" "$SANITIZED_BUILD/CMakeCache.txt"; then
    echo "needle_sim: $SANITIZED_BUILD was configured without clang and the fuzz targets: made anew" >&2
    rm -rf "$SANITIZED_BUILD"
  fi
  if [ ! -f "$SANITIZED_BUILD/CMakeCache.txt" ]; then
    CC=clang CXX=clang++ cmake -S "$ROOT" -B "$SANITIZED_BUILD" -DCMAKE_BUILD_TYPE=RelWithDebInfo "${UNITY[@]}" \
      -DNEEDLE_SIM_SANITIZE=ON -DNEEDLE_SIM_FUZZ=ON -DCATKIN_DEVEL_PREFIX="$SANITIZED_BUILD/devel" \
      -DPYTHON_EXECUTABLE=/usr/bin/python3 -DPython3_EXECUTABLE=/usr/bin/python3 >&2
  fi
}

# The core library and the tool with plain CMake, without ROS (NEEDLE_SIM_ROS=OFF: no catkin;
# NEEDLE_SIM_ROSBAG=OFF: no ROS library at all), in folder $1; further arguments go to cmake
# (a compiler, sanitizer flags). Builds the tool and tutorial 0.
configure_core() {
  local dir="$1"
  shift
  if [ -f "$dir/CMakeCache.txt" ] && ! grep -q "^NEEDLE_SIM_ROS:BOOL=OFF" "$dir/CMakeCache.txt"; then
    echo "needle_sim: $dir was configured with ROS: made anew" >&2
    rm -rf "$dir"
  fi
  if [ ! -f "$dir/CMakeCache.txt" ]; then
    cmake -S "$ROOT" -B "$dir" -DNEEDLE_SIM_ROS=OFF -DNEEDLE_SIM_ROSBAG=OFF -DBUILD_TESTING=ON "${UNITY[@]}" "$@" >&2
  fi
}

# A built no-ROS folder ($1): tutorial 0 through CTest, a shipped scene by name with the
# tool, and nothing of ROS linked.
check_core_build() {
  local dir="$1" out
  (cd "$dir" && ctest --output-on-failure -R tutorial_00_library) >&2
  out="$(mktemp -d /tmp/needle_sim_core.XXXXXX)"
  "$dir/bin/needle_sim" run phantom_insertion_8x4x4.yaml --out "$out" --quiet --set time.duration=0.5
  /usr/bin/python3 - "$out/summary.json" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))
assert s["status"] == "ok" and s["needles"]["needle"]["state"] in ("inserted", "punctured"), s
print("needle_sim (no ROS): ran the scene, %d steps, tip %s" % (s["steps"], s["needles"]["needle"]["state"]))
PY
  if ldd "$dir/bin/needle_sim" "$dir/lib/libneedle_sim_core.so" | grep -Ei "libros|librosbag|libroscpp|catkin|libactionlib|libtf2"; then
    echo "needle_sim: the no-ROS build links ROS libraries (above)" >&2
    return 1
  fi
  echo "needle_sim (no ROS): library and tool link nothing of ROS" >&2
}

NEEDLE_SIM="$DEVEL/lib/needle_sim/needle_sim"

# Runs a command beside a roscore of its own (a free port, logs in a temporary ROS_HOME),
# stopped afterwards: the sanitizer builds' node-threads test (test/rostest/test_node_threads.cpp),
# whose binary is run directly rather than through rostest (which would look for it in the
# regular devel space too).
with_roscore() {
  local port home pid rc=0
  port=$(/usr/bin/python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
  home="$(mktemp -d /tmp/needle_sim_roscore.XXXXXX)"
  ROS_HOME="$home" ROS_MASTER_URI="http://127.0.0.1:$port" roscore -p "$port" >"$home/roscore.log" 2>&1 &
  pid=$!
  local i
  for i in $(seq 100); do
    ROS_MASTER_URI="http://127.0.0.1:$port" rosparam get /run_id >/dev/null 2>&1 && break
    sleep 0.2
  done
  ROS_HOME="$home" ROS_MASTER_URI="http://127.0.0.1:$port" "$@" || rc=$?
  kill -INT "$pid" 2>/dev/null || true
  wait "$pid" 2>/dev/null || true
  rm -rf "$home"
  return $rc
}

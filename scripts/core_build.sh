#!/usr/bin/env bash
# The core library and the needle_sim tool as a user without ROS builds them: plain CMake
# (NEEDLE_SIM_ROS=OFF: no catkin; NEEDLE_SIM_ROSBAG=OFF: no ROS library at all) in
# ./build/core, with only the core's Debian packages. Builds the library, the tool and
# tutorial 0, runs tutorial 0 (CTest) and a shipped scene by name, and checks that neither
# the library nor the tool links anything of ROS. scripts/tsan.sh runs the same
# configuration under ThreadSanitizer in CI.
#   bash scripts/core_build.sh [BUILD_DIR]
set -eo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
PACKAGES=("${CORE_PACKAGES[@]}")
install_missing
CORE_BUILD="${1:-$ROOT/build/core}"
configure_core "$CORE_BUILD" -DCMAKE_BUILD_TYPE=Release
cmake --build "$CORE_BUILD" -j"$(nproc)" --target needle_sim_tool tutorial_00_library >&2
check_core_build "$CORE_BUILD"

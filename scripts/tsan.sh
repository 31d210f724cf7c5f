#!/usr/bin/env bash
# ThreadSanitizer build of the core in ./build/tsan (clang, without ROS: scripts/core_build.sh's
# configuration, whose checks it runs too: tutorial 0, a scene, no ROS linked), then the unit tests that run
# the stepping thread beside background work (#18): the factor refreshed on a background
# thread (test_verification's async trajectories, test_solver), mesh changes built in the
# background and simulations copied while a build is pending (test_adaptivity,
# test_prediction), goal-oriented passes in the background (test_goal_estimate); then the ROS layer's threads (issue #39): test/tsan_ros builds src/ros and
# test/rostest/test_node_threads.cpp with -fsanitize=thread against this core, and runs the test
# beside a roscore of its own. Exits non-zero on any failure or data-race report.
#   bash scripts/tsan.sh                  # the async tests
#   bash scripts/tsan.sh -R test_solver   # extra arguments go to ctest (the node-threads test runs too)
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
PACKAGES+=(clang libclang-rt-14-dev)
install_missing
TSAN_BUILD="${NEEDLE_SIM_TSAN_DIR:-$ROOT/build/tsan}"
# The core without ROS (configure_core: plain CMake, no catkin), as a user without ROS builds
# it: CI's check of that configuration, under ThreadSanitizer.
CC=clang CXX=clang++ configure_core "$TSAN_BUILD" -DCMAKE_BUILD_TYPE=RelWithDebInfo -DNEEDLE_SIM_TSAN=ON
TESTS=(test_solver test_verification test_adaptivity test_prediction)
cmake --build "$TSAN_BUILD" -j"$(getconf _NPROCESSORS_ONLN)" --target "${TESTS[@]}" test_goal_estimate needle_sim_tool \
  tutorial_00_library >&2
cd "$TSAN_BUILD"
# Uninstrumented libraries (OpenBLAS, CHOLMOD, libgomp) synchronise internally in ways TSan
# cannot see: their frames are suppressed (test/tsan.supp); every report in our code fails.
export TSAN_OPTIONS="halt_on_error=1:second_deadlock_stack=1:suppressions=$ROOT/test/tsan.supp"
export OPENBLAS_NUM_THREADS=1 OMP_THREAD_LIMIT=1
check_core_build "$TSAN_BUILD"
ctest --output-on-failure -j1 -R "$(IFS='|'; echo "${TESTS[*]}")" "$@"
# Of test_goal_estimate only the background passes (its static boxes take minutes under TSan).
GTEST_FILTER='*Background*' ctest --output-on-failure -j1 -R test_goal_estimate "$@"

# The ROS layer under ThreadSanitizer. Its generated messages and reconfigure header are the
# regular build's (scripts/test.sh, CI's first phase, made them; made here if missing).
if [ ! -f "$DEVEL/include/needle_sim/SimStatus.h" ] || [ ! -f "$DEVEL/include/needle_sim/LimitsConfig.h" ]; then
  build_generated
fi
TSAN_ROS="${TSAN_BUILD}_ros"
CC=clang CXX=clang++ cmake -S "$ROOT/test/tsan_ros" -B "$TSAN_ROS" "${UNITY[@]}" -DNEEDLE_SIM_CORE_BUILD="$TSAN_BUILD" \
  -DNEEDLE_SIM_GENERATED="$DEVEL/include" -DPYTHON_EXECUTABLE=/usr/bin/python3 -DPython3_EXECUTABLE=/usr/bin/python3 >&2
cmake --build "$TSAN_ROS" -j"$(getconf _NPROCESSORS_ONLN)" >&2
# ROS's libraries are not instrumented: their own accesses are not checked
# (ignore_noninstrumented_modules), our code against them is.
TSAN_OPTIONS="$TSAN_OPTIONS:ignore_noninstrumented_modules=1" with_roscore "$TSAN_ROS/test_node_threads"

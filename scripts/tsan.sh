#!/usr/bin/env bash
# ThreadSanitizer build of the package in ./build/tsan (clang), then the unit tests that run
# the stepping thread beside background work (#18): the factor refreshed on a background
# thread (test_verification's async trajectories, test_solver), mesh changes built in the
# background and simulations copied while a build is pending (test_adaptivity,
# test_prediction). Exits non-zero on any failure or data-race report.
#   bash scripts/tsan.sh                  # the async tests
#   bash scripts/tsan.sh -R test_solver   # extra arguments go to ctest
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
PACKAGES+=(clang libclang-rt-14-dev)
install_missing
TSAN_BUILD="${NEEDLE_SIM_TSAN_DIR:-$ROOT/build/tsan}"
if [ ! -f "$TSAN_BUILD/CMakeCache.txt" ]; then
  CC=clang CXX=clang++ cmake -S "$ROOT" -B "$TSAN_BUILD" -DCMAKE_BUILD_TYPE=RelWithDebInfo -DNEEDLE_SIM_TSAN=ON \
    -DCATKIN_DEVEL_PREFIX="$TSAN_BUILD/devel" \
    -DPYTHON_EXECUTABLE=/usr/bin/python3 -DPython3_EXECUTABLE=/usr/bin/python3 >&2
fi
TESTS=(test_solver test_verification test_adaptivity test_prediction)
cmake --build "$TSAN_BUILD" -j"$(getconf _NPROCESSORS_ONLN)" --target "${TESTS[@]}" >&2
cd "$TSAN_BUILD"
# Uninstrumented libraries (OpenBLAS, CHOLMOD, libgomp) synchronise internally in ways TSan
# cannot see: their frames are suppressed (test/tsan.supp); every report in our code fails.
export TSAN_OPTIONS="halt_on_error=1:second_deadlock_stack=1:suppressions=$ROOT/test/tsan.supp"
export OPENBLAS_NUM_THREADS=1 OMP_THREAD_LIMIT=1
ctest --output-on-failure -j1 -R "$(IFS='|'; echo "${TESTS[*]}")" "$@"

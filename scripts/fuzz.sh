#!/usr/bin/env bash
# libFuzzer runs of the scene parser (with --set overrides) and of mesh loading, with
# AddressSanitizer + UndefinedBehaviorSanitizer (clang), in ./build/asan, the build
# scripts/sanitize.sh makes (issue #8). Each target runs for --seconds (default 60) from its
# corpus under test/data/fuzz/<target>; new coverage goes to build/asan/corpus/<target>,
# crashes to build/asan/crashes/<target>
# (copy each into test/data/fuzz/<target>/ once fixed: CTest replays them).
#   bash scripts/fuzz.sh                  # both targets, 60 s each
#   bash scripts/fuzz.sh --seconds 600    # the long (nightly) mode
#   bash scripts/fuzz.sh --runs 6000      # a fixed number of inputs from seed 1 (CI: repeatable)
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
SECONDS_EACH=60
LIMIT=()
while [ $# -gt 0 ]; do
  case "$1" in
    --seconds) SECONDS_EACH="$2"; shift 2 ;;
    --runs) LIMIT=(-runs="$2" -seed=1); shift 2 ;;
    *) echo "fuzz.sh: unknown argument $1" >&2; exit 2 ;;
  esac
done
configure_sanitized
BUILD="$SANITIZED_BUILD"
cmake --build "$BUILD" -j"$(nproc)" --target fuzz_scene fuzz_mesh >&2
export ASAN_OPTIONS="detect_leaks=1" UBSAN_OPTIONS="print_stacktrace=1:halt_on_error=1"
export LSAN_OPTIONS="suppressions=$ROOT/test/fuzz/lsan.supp:print_suppressions=0"
export OPENBLAS_NUM_THREADS=1 OMP_THREAD_LIMIT=1
status=0
for t in scene mesh; do
  mkdir -p "$BUILD/corpus/$t" "$BUILD/crashes/$t"
  echo "fuzz.sh: fuzz_$t for $SECONDS_EACH s ${LIMIT[*]}" >&2
  "$BUILD/devel/lib/needle_sim/fuzz_$t" -max_total_time="$SECONDS_EACH" "${LIMIT[@]}" -timeout=10 -rss_limit_mb=4096 \
    -artifact_prefix="$BUILD/crashes/$t/" -print_final_stats=1 \
    "$BUILD/corpus/$t" "$ROOT/test/data/fuzz/$t" || status=1
done
exit $status

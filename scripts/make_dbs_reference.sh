#!/usr/bin/env bash
# Regenerates test/data/reference/dbs_fine_stn.csv, the finer run that test_dbs's
# DbsCoarse.TargetErrorBoundCoversTheDifferenceFromTheFineReference measures the coarse run's
# error against (issue #39): dbs_fine.yaml stepped to 9 s with target errors, the left STN
# every 50 steps. Builds test_dbs in ./build (scripts/test.sh's), runs its disabled writer
# test, and names the commit in the file's first line (with "-dirty" when the work tree has
# uncommitted changes: commit first, then regenerate). About 1 min on an idle machine.
# After regenerating, put the commit into the comment above that test and the measured
# ratios into doc/verification.md.
set -eo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BUILD="${NEEDLE_SIM_BUILD_DIR:-$ROOT/build}"
DEVEL="${NEEDLE_SIM_DEVEL_DIR:-$ROOT/devel}"
OUT="${1:-$ROOT/test/data/reference/dbs_fine_stn.csv}"
cmake --build "$BUILD" -j2 --target test_dbs >&2
commit="$(git -C "$ROOT" rev-parse --short=7 HEAD)"
if ! git -C "$ROOT" diff --quiet HEAD -- src include config data; then commit="$commit-dirty"; fi
NEEDLE_SIM_DBS_REFERENCE="$OUT" NEEDLE_SIM_DBS_REFERENCE_COMMIT="$commit" \
  "$DEVEL/lib/needle_sim/test_dbs" --gtest_also_run_disabled_tests --gtest_filter='DbsReference.*' >&2
echo "wrote $OUT (commit $commit)" >&2

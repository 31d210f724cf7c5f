#!/usr/bin/env bash
# The static solve of a scene with needle_sim's stale-factor CG against CG preconditioned by
# HYPRE's BoomerAMG (algebraic multigrid), at equal error (issue #18; doc/benchmarks.md,
# "Static solves"). Installs HYPRE (libhypre-dev, with Debian's MPI), builds
# needle_sim_amg_baseline in ./build (the option NEEDLE_SIM_AMG_BASELINE) and runs it.
#   bash scripts/amg_baseline.sh                                  # the 32x16x16 box, 3 runs each
#   bash scripts/amg_baseline.sh config/scenes/phantom_32x16x16.yaml --set 'tissue.grid.cells=[48,24,24]' --repeat 1
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
PACKAGES+=(libhypre-dev)
install_missing
build
cmake "$BUILD" -DNEEDLE_SIM_AMG_BASELINE=ON >&2
cmake --build "$BUILD" -j"$(nproc)" --target needle_sim_amg_baseline >&2
if [ $# -eq 0 ]; then set -- "$ROOT/config/scenes/phantom_32x16x16.yaml" --repeat 3; fi
# One thread for each method (OpenBLAS under CHOLMOD, OpenMP in HYPRE), as the tool runs.
export OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 OMP_THREAD_LIMIT=1
exec "$DEVEL/lib/needle_sim/needle_sim_amg_baseline" "$@"

#!/usr/bin/env bash
# Install what is missing, build, and run a scene: by default the paper's adaptive phantom
# insertion, with its plots (probe displacement, mesh DOFs and holder force against time) and
# a ParaView series of the tissue and the needle.
# Usage: bash scripts/run.sh [SCENE.yaml] [needle_sim run options...]
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
install_missing
build
SCENE="${1:-$ROOT/config/scenes/phantom_insertion_adaptive.yaml}"
shift || true
NAME="$(basename "$SCENE" .yaml)"
OUT="$ROOT/results/$NAME"
"$NEEDLE_SIM" run "$SCENE" --out "$OUT" --vtu-every 100 "$@"
# in the devel space's environment: the Python package needle_sim
"$DEVEL/env.sh" /usr/bin/python3 "$ROOT/scripts/plot_run.py" "$OUT"
echo "open in ParaView: paraview $OUT/tissue.pvd $OUT/needles.pvd"

#!/usr/bin/env bash
# Install what is missing, build, and run the default scene (the paper's phantom, 8x4x4).
# Usage: bash scripts/run.sh [SCENE.yaml] [needle_sim run options...]
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
install_missing
build
SCENE="${1:-$ROOT/config/scenes/phantom_8x4x4.yaml}"
shift || true
NAME="$(basename "$SCENE" .yaml)"
OUT="$ROOT/results/$NAME"
"$NEEDLE_SIM" run "$SCENE" --out "$OUT" "$@"

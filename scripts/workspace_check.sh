#!/usr/bin/env bash
# The package as a ROS user builds it: copied into a fresh catkin workspace, built and
# installed with catkin_make, then run from the install space with the source tree, the
# build and the devel space out of reach (moved away): one scene with the tool (found by its
# name in the installed share folder), a two-sample `needle_sim ensemble` (the installed
# script on a LocalCluster), and one rostest (the scripted insertion: the node, the
# publisher and the check are installed programs). Part of .ci/run.
# Usage: bash scripts/workspace_check.sh [WORKSPACE]   (default: a new folder under /tmp)
set -eo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
WS="${1:-$(mktemp -d /tmp/needle_sim_ws.XXXXXX)}"
export PATH="/usr/bin:$PATH"  # Debian's python3 (rospy) first, not a pyenv one
echo "workspace_check: catkin workspace in $WS" >&2
rm -rf "$WS/src" "$WS/src.away" "$WS/build" "$WS/devel" "$WS/install"
mkdir -p "$WS/src/needle_sim"
# What git tracks, as it is in the working tree (in CI: a clean clone).
(cd "$ROOT" && git ls-files -z | xargs -0 cp --parents -t "$WS/src/needle_sim")
cd "$WS"
catkin_make -DPYTHON_EXECUTABLE=/usr/bin/python3 -DPython3_EXECUTABLE=/usr/bin/python3 -DCATKIN_ENABLE_TESTING=OFF \
  -DCMAKE_BUILD_TYPE=Release -j"$(nproc)" install > "$WS/catkin_make.log" 2>&1 ||
  { tail -50 "$WS/catkin_make.log" >&2; echo "workspace_check: catkin_make install failed" >&2; exit 1; }
mv src src.away
rm -rf build devel
set +u
# shellcheck disable=SC1091
source install/setup.bash
set -u
TOOL="$WS/install/lib/needle_sim/needle_sim"
"$TOOL" run phantom_insertion_8x4x4.yaml --out "$WS/out" --quiet --set time.duration=0.5
python3 - "$WS/out/summary.json" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))
assert s["status"] == "ok", s
assert s["needles"]["needle"]["state"] in ("inserted", "punctured"), s["needles"]["needle"]["state"]
print("workspace_check: installed tool ran the scene: %d steps, tip state %s" % (s["steps"], s["needles"]["needle"]["state"]))
PY
# needle_sim ensemble from the install space: the installed script and package, the shipped
# scene found by name, a LocalCluster of one worker, two short runs.
"$TOOL" ensemble phantom_insertion_8x4x4.yaml --samples 2 --seed 1 --workers 1 --no-plot \
  --vary "interaction.friction=uniform(0.02,0.1)" --set time.duration=0.5 --out "$WS/ensemble"
python3 - "$WS/ensemble/ensemble.csv" <<'PY'
import csv, sys
rows = list(csv.DictReader(open(sys.argv[1])))
assert [r["status"] for r in rows] == ["ok", "ok"], rows
print("workspace_check: installed needle_sim ensemble ran 2 samples")
PY
rostest needle_sim scripted.test
echo "workspace_check: ok (install space self-contained)" >&2

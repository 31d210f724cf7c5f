#!/usr/bin/env bash
# The package as a ROS user builds it: copied into a fresh catkin workspace, built and
# installed with catkin_make, then run from the install space with the source tree, the
# build and the devel space out of reach (moved away): one scene with the tool (found by its
# name in the installed share folder); the Python package installed beside the generated
# messages (catkin_python_setup) and an installed script (plot_run.py) on the run; a
# two-sample `needle_sim ensemble` (the installed script and package on a LocalCluster) on a
# trajectory aimed by the installed tool (check --aim); and one rostest (the scripted
# insertion: the node, the publisher and the check are installed programs). Part of .ci/run.
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
# The Python package: installed (not the source's), with the generated messages in the same
# package, finding the installed share folder and tool; an installed script runs from there.
python3 - "$WS/install" <<'PY'
import os, sys
import needle_sim.ensemble
from needle_sim import paths
from needle_sim.msg import SimStatus
install = os.path.realpath(sys.argv[1])
for f in (needle_sim.ensemble.__file__, sys.modules["needle_sim.msg"].__file__):
    assert os.path.realpath(f).startswith(os.path.join(install, "lib", "python3", "dist-packages", "needle_sim")), f
assert os.path.realpath(paths.share_dir()) == os.path.join(install, "share", "needle_sim"), paths.share_dir()
assert os.path.realpath(paths.tool()) == os.path.join(install, "lib", "needle_sim", "needle_sim"), paths.tool()
print("workspace_check: installed Python package needle_sim (ensemble, msg) finds", paths.share_dir(), "and", paths.tool())
PY
"$WS/install/lib/needle_sim/plot_run.py" "$WS/out" >/dev/null
test -s "$WS/out/run.png"
echo "workspace_check: installed plot_run.py drew $WS/out/run.png" >&2
# needle_sim ensemble from the install space: the installed script and package, the shipped
# scene found by name, a trajectory aimed by the installed tool (the needle turned about the
# target, its tip still ending on it), a LocalCluster of one worker, two short runs.
cat > "$WS/trajectories.yaml" <<'YAML'
units: mm
target: [20, 10, 10]
trajectories: [{name: tilted, entry: [-2.9, 12, 10]}]
YAML
"$TOOL" ensemble phantom_insertion_8x4x4.yaml --samples 2 --seed 1 --workers 1 --no-plot \
  --vary "interaction.friction=uniform(0.02,0.1)" --set time.duration=0.5 --trajectories "$WS/trajectories.yaml" \
  --out "$WS/ensemble"
python3 - "$WS/ensemble" <<'PY'
import csv, json, os, sys
rows = list(csv.DictReader(open(os.path.join(sys.argv[1], "ensemble.csv"))))
assert [(r["status"], r["trajectory"]) for r in rows] == [("ok", "tilted")] * 2, rows
t = json.load(open(os.path.join(sys.argv[1], "study.json")))["definition"]["trajectories"][0]
assert t["set"][0].startswith("needle.base.position=") and t["angle_to_scene_deg"] > 1, t
print("workspace_check: installed needle_sim ensemble ran 2 samples on a trajectory aimed by the installed tool")
PY
rostest needle_sim scripted.test
echo "workspace_check: ok (install space self-contained)" >&2

#!/usr/bin/env bash
# The docs job of .ci/run: every command block of the README, the tutorials and cli.md run
# as a reader would, and every figure they quote checked (scripts/docs_run.py; long studies
# only with --full: `bash scripts/docs_job.sh --full`). rviz runs under Xvfb. Writes
# docs_run.log (the blocks' output) and docs_report.md (blocks, wall times, figures) in
# ./build. Assumes the build of scripts/test.sh.
set -eo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
cd "$ROOT"
set +u
export PATH="/usr/bin:$PATH"
# shellcheck disable=SC1091
source devel/setup.bash
export ROS_HOME="${ROS_HOME:-$(mktemp -d /tmp/needle_sim_docs_ros.XXXXXX)}"
unset ROS_MASTER_URI  # the docs' launches start the default master, as on a reader's machine
xvfb-run -a -s "-screen 0 1280x1024x24" /usr/bin/python3 scripts/docs_run.py --clean \
  --log "$BUILD/docs_run.log" --report "$BUILD/docs_report.md" "$@" ||
  { echo "docs_job: the end of $BUILD/docs_run.log:" >&2; tail -60 "$BUILD/docs_run.log" >&2; exit 1; }

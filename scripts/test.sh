#!/usr/bin/env bash
# Install what is missing, build, and run the whole test suite (gtest unit tests and
# rostest tests, all registered with CTest). Exits non-zero on any failure.
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
install_missing
build
cd "$BUILD"
# ROS's Python tools (rostest, hztest) start with `#!/usr/bin/env python3`: Debian's
# interpreter must come first, not a pyenv one that has no rospy.
export PATH="/usr/bin:$PATH"
# Two tests at a time (one per core); those on the wall clock run alone (RUN_SERIAL: CMakeLists.txt).
ctest --output-on-failure -j"$(getconf _NPROCESSORS_ONLN)" "$@"

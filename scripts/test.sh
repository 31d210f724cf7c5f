#!/usr/bin/env bash
# Install what is missing, build, and run the whole test suite (gtest unit tests and
# rostest tests, all registered with CTest). Exits non-zero on any failure.
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
install_missing
build
cd "$BUILD"
ctest --output-on-failure "$@"

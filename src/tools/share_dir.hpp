#pragma once
// Where the tool finds the package's files (scenes, meshes): $NEEDLE_SIM_SHARE_DIR if set;
// else beside the executable as installed (<prefix>/lib/needle_sim/needle_sim ->
// <prefix>/share/needle_sim); else the source tree it was built from (devel space). A scene
// named without a folder that does not exist where it is asked for is looked up in
// <share>/config/scenes, ".yaml" optional, so `needle_sim run phantom_insertion_adaptive` works anywhere.
#include <string>

namespace needle_sim {

std::string shareDir();
std::string resolveScene(const std::string& path);
// This executable's path (/proc/self/exe); empty if unknown.
std::string executablePath();
// The Python ensemble tool run by `needle_sim ensemble` (doc/ensemble.md): ensemble.py beside
// the executable (installed: <prefix>/lib/needle_sim/; devel space: catkin's relay to the
// source), else the source tree's scripts/ensemble.py.
std::string ensembleScript();
// Where the Python package needle_sim that goes with this executable is (the folder holding
// needle_sim/): <prefix>/lib/python3/dist-packages beside the executable (install or devel
// space: catkin_python_setup), else the source tree's src/; empty if neither has it.
std::string pythonPackageRoot();

}  // namespace needle_sim

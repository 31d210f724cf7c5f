#pragma once
// Scenes by name, as every front end takes them (the tool, the node, the launch files): the
// path as given when that file exists or the name has a folder; else the package's scene of
// that name, <share>/config/scenes/<name> (".yaml" may be left out); else the name as given
// (the loader then says it cannot open it).
#include <string>

namespace needle_sim {

std::string resolveScenePath(const std::string& name, const std::string& share_dir);

}  // namespace needle_sim

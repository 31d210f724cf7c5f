#include "needle_sim/scene/scene_path.hpp"

#include <filesystem>

namespace needle_sim {

std::string resolveScenePath(const std::string& name, const std::string& share_dir) {
  namespace fs = std::filesystem;
  std::error_code ec;
  if (name.empty() || fs::exists(name, ec) || name.find('/') != std::string::npos || share_dir.empty()) return name;
  const fs::path scenes = fs::path(share_dir) / "config" / "scenes";
  for (const std::string& candidate : {name, name + ".yaml"})
    if (fs::is_regular_file(scenes / candidate, ec)) return (scenes / candidate).string();
  return name;
}

}  // namespace needle_sim

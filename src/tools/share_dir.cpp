#include "share_dir.hpp"

#include "needle_sim/scene/scene_path.hpp"

#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <vector>

namespace needle_sim {

namespace fs = std::filesystem;

std::string executablePath() {
  char buf[4096];
  const ssize_t n = readlink("/proc/self/exe", buf, sizeof buf - 1);
  if (n <= 0) return {};
  buf[n] = 0;
  return buf;
}

std::string shareDir() {
  if (const char* env = std::getenv("NEEDLE_SIM_SHARE_DIR"); env && *env) return env;
  if (const std::string exe = executablePath(); !exe.empty()) {
    // <prefix>/lib/needle_sim/needle_sim (catkin) or <prefix>/bin/needle_sim (plain CMake)
    for (const char* up : {"../..", ".."}) {
      const fs::path installed = fs::path(exe).parent_path() / up / "share" / "needle_sim";
      std::error_code ec;
      if (fs::exists(installed / "config" / "scenes", ec)) return fs::weakly_canonical(installed, ec).string();
    }
  }
  return NEEDLE_SIM_SOURCE_SHARE_DIR;
}

std::string ensembleScript() {
  std::error_code ec;
  if (const std::string exe = executablePath(); !exe.empty()) {
    const fs::path beside = fs::path(exe).parent_path() / "ensemble.py";
    if (fs::exists(beside, ec)) return beside.string();
  }
  return std::string(NEEDLE_SIM_SOURCE_SHARE_DIR) + "/scripts/ensemble.py";
}

std::string pythonPackageRoot() {
  std::error_code ec;
  std::vector<fs::path> candidates;
  if (const std::string exe = executablePath(); !exe.empty())
    candidates.push_back(fs::path(exe).parent_path().parent_path() / "python3" / "dist-packages");
  candidates.push_back(fs::path(NEEDLE_SIM_SOURCE_SHARE_DIR) / "src");
  for (const fs::path& c : candidates)
    if (fs::exists(c / "needle_sim" / "__init__.py", ec)) return fs::weakly_canonical(c, ec).string();
  return {};
}

// The node's and the launch files' rule (scene/scene_path.hpp), ".yaml" optional: the tool's
// own copy of it took "dbs_adaptive.yaml" but not "dbs_adaptive".
std::string resolveScene(const std::string& path) { return resolveScenePath(path, shareDir()); }

}  // namespace needle_sim

// libFuzzer target: the scene parser with `--set` overrides (issue #8). The input is scene
// YAML; lines starting with "@set " are taken out and applied as overrides, as
// `needle_sim run --set`. Every input must either parse or raise InputError (a clear message
// naming the key); anything else (a crash, another exception, a sanitizer report) is a bug.
//
//   scripts/fuzz.sh --seconds 60          # fuzz (clang, libFuzzer, ASan + UBSan)
//   build/devel/lib/needle_sim/fuzz_scene_replay test/data/fuzz/scene   # replay the corpus (CTest)
#include <cstddef>
#include <cstdint>
#include <sstream>
#include <string>
#include <vector>

#include "needle_sim/core/error.hpp"
#include "needle_sim/scene/scene_loader.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string input(reinterpret_cast<const char*>(data), size);
  std::istringstream in(input);
  std::string line, text;
  std::vector<std::string> overrides;
  while (std::getline(in, line)) {
    if (line.rfind("@set ", 0) == 0)
      overrides.push_back(line.substr(5));
    else
      text += line + "\n";
  }
  try {
    // Relative mesh paths resolve next to a scene file in a folder that holds none: surface
    // geometry is fuzzed by fuzz_mesh.
    needle_sim::parseScene(text, "/nonexistent/fuzz/scene.yaml", overrides);
  } catch (const needle_sim::InputError&) {
  }
  return 0;
}

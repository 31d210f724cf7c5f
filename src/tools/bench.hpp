#pragma once
// `needle_sim bench`: median time of one dynamic step, split into phases, on a list of
// grids of one scene (default: the phantom at the paper's three meshes).
#include <string>
#include <vector>

struct BenchOptions {
  std::string scene = "phantom_8x4x4.yaml";  // resolved by resolveScene
  std::vector<std::string> cells{"8x4x4", "16x8x8", "32x16x16"};
  int steps = 30;
  int warmup = 3;
  std::vector<std::string> sets;
  bool compare_direct = false;
  std::string json_out;
};

int benchCommand(const BenchOptions& opts);

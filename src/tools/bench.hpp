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
  int target_error_every = 0;  // adaptive scenes: the goal-oriented target estimate every N steps (timed apart)
  std::vector<double> target;  // x y z: a target added at this planning position (for the estimate)
  // Adaptive scenes: step k starts no sooner than k dt after the first (the node's 1/dt loop
  // on an idle clock), so that background work gets the wall time a real-time run gives it;
  // step times are the steps' own. Off: steps back to back, as fast as the machine allows.
  bool pace = false;
  int slowest = 0;  // also list the N slowest steps with their phases
};

int benchCommand(const BenchOptions& opts);

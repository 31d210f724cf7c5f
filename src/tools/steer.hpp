#pragma once
// `needle_sim steer`: plans a bevel-tip needle's roll-flip insertion to a target on the
// simulator's own prediction (steer/steering_planner.hpp), prints the plan and the predicted
// tip-target distance, then runs the plan live and reports where the tip really ends.
#include <cmath>
#include <string>
#include <vector>

struct SteerOptions {
  std::string scene;
  std::vector<std::string> sets;
  std::string needle;          // default: the first needle
  std::vector<double> target;  // x y z [m], tissue frame
  double speed = 0.01;         // insertion speed [m/s]
  double roll_rate = M_PI;     // base roll rate for the turns [rad/s]
  double dt = 0;               // prediction time step [s] (0: the scene's)
  double tolerance = 2e-4;     // [m]
  int max_predictions = 8;
  bool live = true;            // run the plan live afterwards
  std::string json_out;
};

int steerCommand(const SteerOptions& opts);

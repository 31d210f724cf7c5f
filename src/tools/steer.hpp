#pragma once
// `needle_sim steer`: plans a bevel-tip needle's roll-flip insertion to a target on the
// simulator's own prediction (steer/steering_planner.hpp), prints the plan and the predicted
// tip-target distance, then hands the plan to the command pipeline as the node would (the
// guard with the node's default limits, or --max-speed/--max-angular-speed), runs it live
// when taken and reports where the tip really ends.
#include <cmath>
#include <string>
#include <vector>

struct SteerOptions {
  std::string scene;
  std::vector<std::string> sets;
  std::string needle;          // default: the first needle
  std::vector<double> target;  // x y z [m], tissue frame
  double speed = 0.01;         // insertion speed [m/s]
  double roll_rate = 0;        // base roll rate for the turns [rad/s] (0: max_angular_speed, at most pi)
  double max_speed = 0.05;     // the live run's guard limits [m/s], [rad/s] (the node's defaults)
  double max_angular_speed = 1.0;
  double dt = 0;               // prediction time step [s] (0: the scene's)
  double tolerance = 2e-4;     // [m]
  int max_predictions = 8;
  bool live = true;            // run the plan live afterwards
  std::string json_out;
};

int steerCommand(const SteerOptions& opts);

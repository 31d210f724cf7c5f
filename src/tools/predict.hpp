#pragma once
// `needle_sim predict`: runs a scene to a time, then predicts a straight insertion plan from
// there on a copy of the simulation (what the ROS node's `predict` service does), several
// times, and reports the median copy and run times; optionally the same plan at the scene's
// own time step, to show what the coarser prediction step costs in accuracy.
#include <string>
#include <vector>

struct PredictOptions {
  std::string scene;
  std::vector<std::string> sets;
  std::string needle;           // default: the first needle
  double at = 0;                // live run to this time first [s]
  double advance = 0.02;        // the plan: the base advances this far along its axis [m] ...
  double over = 0;              // ... over this long [s] (0: the whole duration)
  double duration = 10;         // simulated time of the prediction [s]
  double dt = 0.01;             // prediction time step [s] (0: the scene's)
  double sample_period = 0.1;   // [s]
  std::vector<double> target;   // x y z: a target to add (planning position) [m]
  int repeat = 5;
  bool compare = false;         // also predict at the scene's dt and report the differences
  std::string csv;              // write the samples of the last prediction here
  std::string json_out;
};

int predictCommand(const PredictOptions& opts);

#pragma once
// `needle_sim calibrate`: fits numeric scene keys so that the simulated axial holder force
// matches a recorded one (doc/calibration.md). Writes DIR/calibration.json, DIR/fit.csv and
// DIR/fit.png, and prints the --set line that reproduces the fit.
#include <string>
#include <vector>

#include "needle_sim/calibration/force_calibration.hpp"

struct CalibrateOptions {
  std::string scene, data, out;
  std::vector<std::string> sets, fit, starts, bounds;
  std::string needle;  // default: the first
  std::string pose_topic, wrench_topic;  // a bag record: commanded poses and measured wrench
  int max_evaluations = 200;
  double xtol_rel = 1e-3;
  bool plot = true;
  bool quiet = false;
};

int calibrateCommand(const CalibrateOptions& o);

// The keys of comma-separated lists with their --start key=value and --bounds key=lo:hi
// (InputError naming the option: a malformed one, a key not in the lists).
std::vector<needle_sim::CalibrationParameter> parseFitKeys(const std::vector<std::string>& lists, const std::vector<std::string>& starts,
                                               const std::vector<std::string>& bounds);

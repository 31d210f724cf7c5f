#pragma once
// `needle_sim run SCENE --data FILE --assimilate KEYS`: the run estimates the keys from the
// measured holder force as it arrives (calibration/force_assimilation.hpp,
// doc/calibration.md#assimilation). Writes DIR/assimilation.csv (an estimate per checkpoint),
// DIR/innovation.csv (every sample against the estimate in force before it arrived) and
// summary.json's "assimilation".
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "needle_sim/calibration/force_assimilation.hpp"

struct AssimilateOptions {
  std::string data;                              // CSV as calibrate's (t, axial_force)
  std::vector<std::string> keys, starts, bounds; // --assimilate k1,k2 --start k=v --bounds k=lo:hi
  double noise = std::numeric_limits<double>::quiet_NaN();  // [N]; NaN: from the residuals
  double tip_noise = std::numeric_limits<double>::quiet_NaN();  // [m] per coordinate, for tip_x,y,z columns
  double target_noise = std::numeric_limits<double>::quiet_NaN();  // [m] per coordinate, for <target>_x,y,z
  double shape_noise = std::numeric_limits<double>::quiet_NaN();   // [m] per coordinate, a bag's --shape-topic
  double every = 0;                              // checkpoint spacing [s]; 0: a tenth of the data
  bool target_error = false;                     // run --target-error: the bound joins the targets' covariance
  bool given() const { return !keys.empty(); }
};

// The estimator for a run of `scene` with `sets` (InputError for bad options or data). With a
// bag's session, `data` may be empty: its measured force and commands are used instead.
std::unique_ptr<needle_sim::ForceAssimilation> makeAssimilation(const AssimilateOptions& o, const std::string& scene,
                                                                const std::vector<std::string>& sets, int needle,
                                                                const needle_sim::ForceRecord* bag_force,
                                                                const std::vector<needle_sim::RecordedCommand>* commands,
                                                                const std::vector<std::string>& target_names);

// Writes DIR/assimilation.csv, DIR/innovation.csv (with a tip or targets measured,
// innovation_tip.csv, innovation_targets.csv) and summary.json's "assimilation" section;
// prints the final estimate.
void writeAssimilation(const needle_sim::ForceAssimilation& a, const AssimilateOptions& o, const std::string& out_dir,
                       const std::vector<std::string>& target_names);

#pragma once
// Records a run of a Simulation and writes its results (doc/cli.md), every figure read from
// the step's Observables (observables.hpp: one sign for the holder force):
//   DIR/timeseries.csv  one row per step (step, t, dofs, step_ms, split timings, solver
//                       counters, NAME_ux, NAME_uy, NAME_uz per probe, per needle its tip,
//                       the force and moment on its holder and NAME_axial_force, per target
//                       its position and the distance to every needle's tip)
//   DIR/summary.json    scene, names in scene order, sizes, step-time statistics, solver
//                       statistics, the final needles, probes and targets
// The CSV is written to timeseries.partial.csv while running and renamed only on success;
// With --centerline, DIR/centerline.csv holds every needle node per step (step, t, needle,
// node, s = rest arc length from the base, x, y, z). With --wrench-rate, DIR/wrench.csv holds
// each needle's force and moment on its holder at that rate, between the steps extrapolated
// from the commanded base motion (needle/holder_wrench.hpp). A failed run leaves summary.json with "status": "numerical_failure" and the step, so
// nothing half-done looks like a result.
#include <fstream>
#include <map>
#include <string>
#include <vector>

#include <memory>

#include <functional>

#include "needle_sim/adapt/spr_estimator.hpp"
#include "needle_sim/needle/holder_wrench.hpp"
#include "needle_sim/core/run_statistics.hpp"
#include "needle_sim/sim/observables.hpp"
#include "needle_sim/sim/simulation.hpp"

namespace needle_sim {


struct RecorderOptions {
  bool centerline = false;      // DIR/centerline.csv: every needle node at every step
  bool error_estimate = false;  // SPR estimate every step: eta_global, eta_max columns
  bool vtu = false;             // DIR/tissue.vtu at the end (stress, eta, level)
  int vtu_every = 0;            // > 0: a ParaView series, DIR/vtu/*_NNNNNN.vt[up] every this many steps and
                                // DIR/tissue.pvd, DIR/needles.pvd (and DIR/surface.pvd for an organ)
  bool target_error = false;    // goal-oriented estimate of each target's error: <name>_err_* columns
  int target_error_every = 1;   // ... every this many steps (the last pass's values in between)
  double wrench_rate = 0;       // > 0 [Hz]: DIR/wrench.csv, the holder wrenches at this rate
};

class RunRecorder {
 public:
  // Creates DIR if needed and removes results of an earlier run there.
  using Options = RecorderOptions;
  RunRecorder(const Simulation& sim, const std::string& dir, const Options& options = {});
  void recordStep(const StepStats& s, double step_ms);
  // Finalises: success writes summary.json and renames the CSV.
  void finish(double wall_s);
  void fail(double wall_s, long step, const std::string& message);

  // Step times, their deadline (dt) and its misses.
  const RunStatistics& stepTimes() const { return step_ms_; }
  // The observables of the last recorded step (what its timeseries.csv row holds).
  const Observables& observables() const { return obs_; }
  std::string summaryPath() const { return dir_ + "/summary.json"; }
  std::string timeseriesPath() const { return dir_ + "/timeseries.csv"; }

 private:
  struct Row {
    const Observables& obs;
    double ms;
  };
  using Writer = std::function<void(std::ostream&, const Row&)>;
  struct Column {
    std::string name;
    Writer write;
  };
  void declareColumns();
  void writeSeriesStep();  // one step of the ParaView series
  void writeWrenches();    // wrench.csv: this step's row and those until the next step
  void writeSeriesIndex() const;
  void writeSummary(const std::string& status, double wall_s, long fail_step, const std::string& message);

  const Simulation& sim_;
  Options options_;
  bool estimate_ = false;  // eta columns (error output asked for, or adaptivity)
  bool target_error_ = false;  // <name>_err_* columns (asked for, or goal-oriented adaptivity)
  double eta_last_ = 0, eta_max_last_ = 0, eta_rel_max_ = 0;
  int max_tissue_dofs_ = 0, mesh_changes_ = 0;
  long refined_total_ = 0, coarsened_total_ = 0;
  RunStatistics adapt_ms_;
  std::string dir_;
  std::ofstream csv_, centerline_, wrench_;
  std::vector<HolderWrenchExtrapolation> wrench_models_;  // per needle (--wrench-rate)
  std::vector<Column> columns_;
  std::vector<std::pair<double, std::string>> series_tissue_, series_needles_, series_surface_;
  Observables obs_;
  RunStatistics step_ms_, forces_ms_, assemble_ms_, factor_ms_, solve_ms_;
  long linear_iterations_ = 0, factorizations_ = 0, newton_iterations_ = 0;
  long async_factorizations_ = 0, factor_waits_ = 0;
  double factor_wait_ms_max_ = 0;
  int max_linear_iterations_ = 0;
  double max_linear_residual_ = 0;
  long constraint_iterations_ = 0;
  int max_constraint_points_ = 0;
  double max_constraint_residual_ = 0;
  long constraint_unconverged_ = 0;  // steps whose constraint solve missed its tolerance
  RunStatistics constraint_ms_;
  std::map<std::string, double> min_target_distance_;  // "target/needle" -> closest tip approach
};

}  // namespace needle_sim

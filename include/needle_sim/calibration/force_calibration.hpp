#pragma once
// Calibration of scene parameters from a recorded insertion (doc/calibration.md): find the
// values of chosen numeric scene keys (e.g. interaction.cutting_force, .grip_pressure,
// tissue.material.young) for which the simulated axial holder force matches a measured one,
// the scene's own needle motion being the recorded robot motion.
//
// A least-squares fit, min sum_i (F_sim(t_i; p) - F_i)^2 over the measured samples, by NLopt's
// BOBYQA (Powell 2009: a derivative-free trust-region method on quadratic models, with
// bounds): the simulated force is a piecewise-smooth function of the parameters (shaft points
// are laid, the tip punctures, at discrete steps), so finite-difference gradients are not
// trusted during the search. At the optimum, standard errors come from a central-difference
// Jacobian J of the residuals: Cov = s^2 (J^T J)^-1, s^2 = RSS / (m - n). A direction in which
// J^T J is (numerically) singular, or a standard error larger than the value itself, marks a
// parameter the data cannot identify.
//
// Every evaluation builds its simulation from the scene file again (the same initial state;
// runs are deterministic). An evaluation that fails numerically is a penalised point.
#include <functional>
#include <limits>
#include <string>
#include <vector>

#include "needle_sim/calibration/force_record.hpp"
#include "needle_sim/core/types.hpp"
#include "needle_sim/sim/command_replay.hpp"

namespace needle_sim {

struct CalibrationParameter {
  std::string key;
  // NaN: the start from the scene (after --set), the bounds from the key's declared range
  // (scene/scene_keys.hpp).
  double start = std::numeric_limits<double>::quiet_NaN();
  double lower = std::numeric_limits<double>::quiet_NaN();
  double upper = std::numeric_limits<double>::quiet_NaN();
  // BOBYQA's initial trust radius in the key's units; NaN: a quarter of the start's scale
  // (a warm start with a known standard deviation takes a few of those).
  double initial_step = std::numeric_limits<double>::quiet_NaN();
  // The search's unit for the key; NaN: |start| (1 for a start of 0). A warm start keeps the
  // nominal value's.
  double scale = std::numeric_limits<double>::quiet_NaN();
  // An absolute stop on the key's change (its units), besides xtol_rel; NaN: none.
  double tolerance = std::numeric_limits<double>::quiet_NaN();
};

struct CalibrationSettings {
  std::string scene;
  std::vector<std::string> sets;  // fixed overrides
  std::vector<CalibrationParameter> parameters;
  int needle = 0;
  int max_evaluations = 200;
  double xtol_rel = 1e-3;  // BOBYQA's stop on the parameters, relative to their scale
  int threads = 2;         // Jacobian evaluations in parallel
  // The measurement's noise (standard deviation [N]): the covariance's s^2 when given; NaN:
  // s^2 = RSS / (m - n), the residuals' own estimate.
  double noise = std::numeric_limits<double>::quiet_NaN();
  // A recorded session's commands (a bag): they drive the needle through the command guard
  // instead of the scene's motion. Empty: the scene's motion.
  std::vector<RecordedCommand> commands;
};

// The simulated axial force on the holder (observe()'s NeedleObservation::axial_force:
// negative when the tissue resists the insertion) and the base's advance along its initial
// axis, at every step.
struct SimulatedForce {
  std::vector<double> t, force, advance;
  std::vector<Vec3> target_end;  // the targets' positions at the last step run
  // With target_errors: per target, the goal-oriented bound on each component of its
  // displacement's discretisation error at the last step (TargetError::component_bound);
  // NaN where the estimate failed. Empty otherwise.
  std::vector<Vec3> target_end_bound;
  bool failed = false;
  std::string failure;
};

struct CalibrationResult {
  std::vector<CalibrationParameter> parameters;  // resolved starts and bounds
  std::vector<double> values, std_errors;        // std error +inf: not identifiable
  Eigen::MatrixXd covariance;                    // s^2 (J^T J)^+ in the keys' units (see std_errors)
  std::vector<bool> identifiable;
  double rms_start = 0, rms = 0;  // RMS residual [N] at the start and the fit
  VecX residuals_fit;             // fitted - measured at the samples inside the simulated time
  int residuals = 0;              // measured samples inside the simulated time
  int evaluations = 0, failed_evaluations = 0, jacobian_evaluations = 0;
  double wall_s = 0;
  std::string stop_reason;
  SimulatedForce start_run, fitted_run;
};

// Starts and bounds of the parameters; InputError for a key unknown to the scene, a key that
// is not a real number (e.g. an integer or a string), a start outside its bounds.
std::vector<CalibrationParameter> resolveParameters(const CalibrationSettings& s);

// One run of the scene with `sets` (later entries win) up to `until` seconds (or its end);
// with commands, they drive the needle (from its rest pose) for `until` seconds; with
// target_errors, the targets' discretisation error bounds at the last step too.
SimulatedForce simulateHolderForce(const std::string& scene, const std::vector<std::string>& sets, int needle,
                                   double until, const std::vector<RecordedCommand>* commands = nullptr,
                                   bool target_errors = false);

// progress(evaluation, rms [N], values) after every evaluation.
CalibrationResult calibrate(const CalibrationSettings& s, const ForceRecord& data,
                            const std::function<void(int, double, const std::vector<double>&)>& progress = {});

// "key=value" overrides of the values (17 significant digits: reproduces the fit exactly).
std::vector<std::string> parameterSets(const std::vector<CalibrationParameter>& p, const std::vector<double>& v);

}  // namespace needle_sim

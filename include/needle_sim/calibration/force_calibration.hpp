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
// Smoothness: the central difference's two halves, forward (r(p + h) - r(p)) / h and backward
// (r(p) - r(p - h)) / h, agree to second order where the residuals are smooth in a key. Where
// an event whose timing moves with the key (a puncture, a shaft point laid, the grip's release)
// falls between, they do not, and the Jacobian measures the jump, not the slope: the
// linearised standard error is then far too small (the cost is rough at that scale and its
// local minima lie closer together than h). The key's roughness, |fwd - bwd| / (|fwd| + |bwd|)
// in [0, 1], above kRoughness marks it rough, and its standard error (and covariance) is
// floored at the step h: the data cannot place it more finely than the events it moves.
//
// Every evaluation builds its simulation from the scene file again (the same initial state;
// runs are deterministic). An evaluation that fails numerically is a penalised point.
#include <atomic>
#include <functional>
#include <stdexcept>
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

// A target added or moved during a session (Simulation::setTarget: a name and its planning,
// rest, position): every run of a fit sets it before its first step, as the session did, so
// that the estimate's prediction covers it (the targets' order: the scene's, then those added).
struct TargetEdit {
  std::string name;
  Vec3 planned = Vec3::Zero();
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
  // A tracked tip's noise (standard deviation per coordinate [m]). A record with both the
  // force and the tip needs both noises: the tip's residuals are weighted by noise / tip_noise
  // (in newtons, the force's units); a record of the tip alone is fitted in metres, with
  // tip_noise as its s (NaN: the residuals' own).
  double tip_noise = std::numeric_limits<double>::quiet_NaN();
  // A measured target position's noise (standard deviation per coordinate [m]), weighed as the
  // tip's. A measured target has an unknown offset from the model's (the brain shift
  // mispredicted, a registration error): it is estimated with the keys, in closed form (the
  // mean of measured - simulated, profiled out of the cost), so the target's samples inform the
  // keys through its motion only.
  double target_noise = std::numeric_limits<double>::quiet_NaN();
  // A measured shape's noise (standard deviation per coordinate of each point [m]), weighed as
  // the tip's.
  double shape_noise = std::numeric_limits<double>::quiet_NaN();
  // A recorded session's commands (a bag): they drive the needle through the command guard
  // instead of the scene's motion. Empty: the scene's motion.
  std::vector<RecordedCommand> commands;
  // The limits the commands are followed with (the node's ~max_speed etc.; the defaults are
  // the node's defaults).
  CommandLimits limits;
  // Set by another thread: every run stops at its next step (failed, "cancelled") and
  // calibrate() throws CalibrationCancelled (the node's estimator at shutdown or ~reset).
  const std::atomic<bool>* cancel = nullptr;
  // Targets set during the session (the node's ~set_target), replayed in order on every run.
  std::vector<TargetEdit> target_edits;
};

// The simulated axial force on the holder (observe()'s NeedleObservation::axial_force:
// negative when the tissue resists the insertion) and the base's advance along its initial
// axis, at every step.
struct SimulatedForce {
  std::vector<double> t, force, advance;
  std::vector<Vec3> tip;         // the needle's tip (observables' NeedleObservation::tip)
  std::vector<std::vector<Vec3>> targets;  // per target, per step: its position
  std::vector<Vec3> target_end;  // the targets' positions at the last step run
  // With a CentreLineRequest: the needle's centre line at its points, at the steps it asked
  // for (their times in shape_t); centreLineAt() interpolates.
  std::vector<double> shape_t;
  std::vector<std::vector<Vec3>> shape;
  // With target_errors: per target, the goal-oriented bound on each component of its
  // displacement's discretisation error at the last step (TargetError::component_bound);
  // NaN where the estimate failed. Empty otherwise.
  std::vector<Vec3> target_end_bound;
  bool failed = false;
  std::string failure;
};

// Roughness above which a key's standard error is floored at its Jacobian step (see above;
// smooth records give below 1e-6, a DBS cannula's withdrawal 0.7 to 1).
constexpr double kRoughness = 0.25;
// |fwd - bwd| / (|fwd| + |bwd|): 0 for equal halves, 1 for one half zero or opposite ones; 0
// when both are zero.
double residualRoughness(const VecX& fwd, const VecX& bwd);

struct CalibrationResult {
  std::vector<CalibrationParameter> parameters;  // resolved starts and bounds
  std::vector<double> values, std_errors;        // std error +inf: not identifiable
  std::vector<double> roughness;                 // per key, in [0, 1]; NaN: not measured
  std::vector<double> jacobian_steps;            // per key: h [the key's units]
  Eigen::MatrixXd covariance;                    // s^2 (J^T J)^+ in the keys' units (see std_errors)
  std::vector<bool> identifiable;
  // Residuals are in the reference channel's units (MeasurementWeights): N with a force.
  double rms_start = 0, rms = 0;  // RMS residual at the start and the fit
  VecX residuals_fit;             // fitted - measured at the samples inside the simulated time
  int residuals = 0;              // residuals (a force sample gives one, a tip sample three)
  // Per residual: its row in the data and its channel (0: force; 1, 2, 3: the tip's x, y, z;
  // 4 + 3 j + c: target j's coordinate c; -1: a coordinate of a measured shape's point).
  std::vector<int> residual_row, residual_channel;
  // Per target: its estimated offset (measured - simulated, at the fit) [m]; NaN: not measured.
  std::vector<Vec3> target_offsets;
  int offset_parameters = 0;  // 3 per measured target: the residuals' degrees of freedom less
  int evaluations = 0, failed_evaluations = 0, jacobian_evaluations = 0;
  double wall_s = 0;
  std::string stop_reason;
  SimulatedForce start_run, fitted_run;
};

// How a record's channels are weighed into one least-squares cost (force_calibration.cpp):
// the reference channel is the force if the record has one, else the tip; its noise is the
// covariance's s (NaN: the residuals' own); the tip's residuals are multiplied by tip_weight.
struct MeasurementWeights {
  double noise = std::numeric_limits<double>::quiet_NaN();
  double tip_weight = 1, target_weight = 1, shape_weight = 1;
  const char* units = "N";
};
// The reference channel: the force, else the tip, else the targets, else the shape. InputError for a record
// of several channels without all their noises, or a noise that is not a positive number.
MeasurementWeights measurementWeights(const CalibrationSettings& s, const ForceRecord& data);

// Starts and bounds of the parameters; InputError for a key unknown to the scene, a key that
// is not a real number (e.g. an integer or a string), a start outside its bounds.
std::vector<CalibrationParameter> resolveParameters(const CalibrationSettings& s);

struct CalibrationCancelled : std::runtime_error {
  CalibrationCancelled() : std::runtime_error("cancelled") {}
};

// One run of the scene with `sets` (later entries win) up to `until` seconds (or its end);
// with commands, they drive the needle (from its rest pose) for `until` seconds, through a
// command pipeline with `limits`; with target_errors, the targets' discretisation error bounds
// at the last step too; cancel set: the run stops at its next step (failed, "cancelled");
// centre_line wanted: the needle's centre line at its points and steps; target_edits set
// before the first step.
SimulatedForce simulateHolderForce(const std::string& scene, const std::vector<std::string>& sets, int needle,
                                   double until, const std::vector<RecordedCommand>* commands = nullptr,
                                   bool target_errors = false, const CommandLimits& limits = CommandLimits{},
                                   const std::atomic<bool>* cancel = nullptr,
                                   const CentreLineRequest& centre_line = CentreLineRequest{},
                                   const std::vector<TargetEdit>& target_edits = {});

// The run's centre line (SimulatedForce::shape) at time x, linearly between the recorded steps
// (clamped at the ends); empty when none was recorded.
std::vector<Vec3> centreLineAt(const SimulatedForce& f, double x);

// progress(evaluation, rms [N], values) after every evaluation.
CalibrationResult calibrate(const CalibrationSettings& s, const ForceRecord& data,
                            const std::function<void(int, double, const std::vector<double>&)>& progress = {});

// "key=value" overrides of the values (17 significant digits: reproduces the fit exactly).
std::vector<std::string> parameterSets(const std::vector<CalibrationParameter>& p, const std::vector<double>& v);

}  // namespace needle_sim

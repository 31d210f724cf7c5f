#pragma once
// Online estimation of uncertain scene parameters from a measured holder force and/or a tracked
// tip position, as they arrive (doc/calibration.md#assimilation, `needle_sim run SCENE --data
// FILE --assimilate KEYS`). The channels are weighed by their stated noises
// (MeasurementWeights, force_calibration.hpp): residuals, RMS and innovations below are in the
// reference channel's units (N with a force; m for a tip alone).
//
// A causal, expanding-window least-squares estimator on calibrate's machinery
// (force_calibration.hpp): at every checkpoint t_k (a fixed spacing of the data's time) the
// keys are fitted to the samples with t <= t_k only, BOBYQA warm-started from the previous
// estimate within the keys' bounds, and the covariance is s^2 (J^T J)^-1 at the fit, s the
// stated noise (or, not stated, the residuals' own estimate). Because the needle-tissue model is quasi-static and deterministic, the fit over
// the whole window is the maximum-likelihood estimate given the data so far (Gaussian noise);
// a recursive filter would linearise what the window fit solves exactly.
//
// Robustness: rows with a non-finite value or a stale time are skipped and counted by the
// reader; a sample whose residual at the fit exceeds `outlier_gate` times the larger of the
// stated noise and the residuals' robust scale (1.4826 median |residual|) is rejected (counted, never used again) and the window refitted. A fit whose residuals stay
// well above the stated noise (RMS > 1.5 sigma, 10 samples or more), all of them or one
// sensor's against its own noise (10 values or more), is flagged inconsistent:
// the model does not fit the measurement, and the estimate must not be trusted silently; its
// covariance then takes the residuals' own scale (RSS / (m - n)) instead of the stated noise's,
// and the next checkpoint's search is not confined to its deviations.
//
// A measured target (its position in the record, e.g. from an image) has an offset from the
// model's, estimated with the keys (the mean of measured - simulated: force_calibration.hpp).
//
// At each checkpoint the scene is also run to its end with the estimate: the targets' final
// positions (plus a measured target's offset), and their covariance from the parameters' (G
// Cov G^T, G by forward differences; for a measured target, of its end less its mean at the
// sampled times, which the offset pins to the measurements) plus the offset's sampling
// variance (s^2 / samples per axis);
// with target_errors, plus the discretisation's: diag(b^2), b the goal-oriented bound on each
// component of the target's displacement error at the end (each bound taken as one standard
// deviation). Without it the covariance has the rank of the keys' (below 3 for one or two keys:
// flat), and says nothing of the mesh.
#include <cmath>
#include <functional>
#include <string>
#include <vector>

#include "needle_sim/calibration/force_calibration.hpp"
#include "needle_sim/core/types.hpp"

namespace needle_sim {

struct AssimilationCheckpoint;

struct AssimilationSettings {
  CalibrationSettings fit;  // scene, sets, keys (starts: the nominal values), needle, commands, noise
  double every = 0;         // checkpoint spacing [s of data]; <= 0: a tenth of the data's span
  double outlier_gate = 10; // residual / noise beyond which a sample is rejected
  bool predict_targets = true;
  bool target_errors = false;  // add the discretisation bound at the end to the targets' covariance
  // Called at each checkpoint once the parameters are fitted (values, stds, consistency,
  // innovations set), before the targets' prediction is run (the node adopts them then).
  std::function<void(const AssimilationCheckpoint&)> on_fit;
};

struct AssimilationCheckpoint {
  double t = 0;                  // the estimate uses the samples with time <= t
  int samples = 0;               // samples used (outliers excluded)
  int new_samples = 0;           // since the previous checkpoint
  std::vector<double> values;    // per key
  std::vector<double> stds;      // +inf: the data do not determine the key yet; inconsistent: inflated
  std::vector<double> roughness; // per key (CalibrationResult::roughness): above kRoughness, std floored
  double rms = 0;                // RMS residual at the fit
  double innovation_rms = 0;     // the new samples against the previous estimate's prediction
  // ... per sensor, in its own units: RMS of measured - predicted per value (the force [N]; a
  // coordinate of the tip, the measured targets, the shape's points [m]); NaN: no new sample.
  double innovation_force = NAN, innovation_tip = NAN, innovation_target = NAN, innovation_shape = NAN;
  bool consistent = true;        // rms <= 1.5 noise, and each sensor's against its own (or too few samples to tell)
  int evaluations = 0;           // simulations of the fit, its Jacobian and the target prediction
  double wall_s = 0;
  std::vector<Vec3> target_end;  // per target: its position at the scene's end with the estimate
  std::vector<Mat3> target_cov;  // ... its covariance: the parameters' (+ the discretisation's) [m^2]
  std::vector<Vec3> target_bound;  // with target_errors: the discretisation bound per component [m]
  // Per target: its offset (measured - modelled) estimated from its measured positions, in
  // target_end and (with its sampling variance) in target_cov; NaN: not measured yet.
  std::vector<Vec3> target_offset;
};

struct AssimilationSample {
  double t = 0, measured = 0;  // the force; NaN: the row has no force sample
  double predicted = 0;  // by the estimate in force before the sample arrived (causal)
  bool arrived = false;  // reached a checkpoint: a sample after the run's end never does
  bool rejected = false;
  Vec3 tip_measured = Vec3::Constant(NAN);  // NaN: the row has no tip sample
  Vec3 tip_predicted = Vec3::Zero();
  bool tip_rejected = false;
  // Per target with measurement columns (else empty): measured (NaN: no sample), predicted (the
  // model's with the offset estimated before the sample arrived), rejected.
  std::vector<Vec3> target_measured, target_predicted;
  std::vector<char> target_rejected;
  // A measured shape (ForceRecord::shape: points back from the tip; empty: none in the row),
  // its prediction, rejected (all its points, when one is an outlier).
  std::vector<Vec3> shape_measured, shape_predicted;
  bool shape_rejected = false;
  bool hasShape() const { return !shape_measured.empty(); }
  bool hasForce() const { return std::isfinite(measured); }
  bool hasTip() const { return tip_measured.allFinite(); }
  bool hasTarget(size_t j) const { return j < target_measured.size() && target_measured[j].allFinite(); }
};

class ForceAssimilation {
 public:
  // `data` as read (readForceCsv with rejects); the noises NaN (not stated) or > 0, both stated
  // for a record of the force and the tip.
  ForceAssimilation(AssimilationSettings s, ForceRecord data);

  // The measurement has arrived up to time t: a checkpoint (a refit) at every checkpoint time
  // passed with enough samples. Returns the number of checkpoints made.
  int advance(double t);
  // The run ended at time t: a last checkpoint at min(t, the data's end) if samples arrived
  // since the last one.
  void finish(double t);

  // Streaming (the node, doc/ros_api.md "Assimilation"): the data grow as they arrive.
  // append(): rows measured after the data's last time, in increasing time, with the
  // channels the data were made with (a channel they lack is NaN). setCommands(): the
  // commands the session followed so far (the base poses the node's needle took), replacing
  // the settings'; the next checkpoint's innovations come from the last estimate run over
  // them. update(): a checkpoint at t (the data's end at most) if samples arrived since the
  // last one, whatever the spacing `every`.
  void append(const ForceRecord& rows);
  void setCommands(std::vector<RecordedCommand> commands);
  // The targets set during the session so far (the node's ~set_target), replacing the
  // settings': the next checkpoint's runs set them, and its prediction covers them.
  void setTargetEdits(std::vector<TargetEdit> edits);
  void update(double t);

  const std::vector<CalibrationParameter>& parameters() const { return params_; }
  const std::vector<AssimilationCheckpoint>& checkpoints() const { return checkpoints_; }
  const std::vector<AssimilationSample>& samples() const { return samples_; }
  std::vector<double> values() const;  // the latest estimate (the nominal values before the first)
  long outliers() const { return outliers_; }
  double every() const { return every_; }
  const MeasurementWeights& weights() const { return w_; }

 private:
  void checkpoint(double t);
  bool stated() const { return !std::isnan(w_.noise); }
  // shape: the needle's centre line at the data's shape points, every step.
  SimulatedForce run(const std::vector<double>& v, double until, bool target_errors = false, bool shape = false) const;
  double end() const;  // the time a run "to the end" stops at

  AssimilationSettings s_;
  ForceRecord data_;
  MeasurementWeights w_;
  std::vector<CalibrationParameter> params_;
  std::vector<AssimilationSample> samples_;
  std::vector<AssimilationCheckpoint> checkpoints_;
  double every_ = 0, next_ = 0, fitted_until_ = -1;
  long outliers_ = 0;
  SimulatedForce prediction_;  // the latest estimate's run over the whole scene
  double predicted_until_ = 0; // ... the time it was run to
  std::vector<Vec3> offsets_;  // the measured targets' latest offsets (NaN: none yet)
};

}  // namespace needle_sim

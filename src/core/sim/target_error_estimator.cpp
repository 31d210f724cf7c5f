#include "needle_sim/sim/target_error_estimator.hpp"

#include <algorithm>
#include <cmath>

namespace needle_sim {

TargetErrorEstimator::TargetErrorEstimator(const TargetErrorEstimator& o)
    : default_radius_(o.default_radius_),
      errors_(o.errors_),
      steps_(o.steps_.size(), -1),
      errors_step_(-1),
      ever_(o.ever_),
      last_step_(o.last_step_),
      shift_errors_(o.shift_errors_) {}

void TargetErrorEstimator::forget() {
  qois_.clear();
  duals_.clear();
  errors_step_ = -1;
  goal_primal_step_ = -1;
  steps_.assign(steps_.size(), -1);
}

void TargetErrorEstimator::targetsChanged() {
  qois_.clear();
  steps_.assign(steps_.size(), -1);
}

const TargetError& TargetErrorEstimator::of(int i, const TargetErrorState& s) {
  const size_t n = s.points.numTargets();
  if (errors_.size() != n || steps_.size() != n) {
    errors_.resize(n);
    steps_.resize(n, -1);
  }
  if (steps_[i] == s.step && errors_step_ != -1) return errors_[i];
  const HexMesh& mesh = s.body.mesh();
  if (qois_.size() != n) {
    const PointLocator locator(mesh);
    qois_.clear();
    for (int k = 0; k < static_cast<int>(n); ++k)
      qois_.push_back(targetQoi(mesh, locator, s.points.target(k).planned, radius(k, s.points)));
  }
  const Estimated in = estimated(s);
  if (duals_.size() != n) duals_.resize(n);
  Eigen::MatrixXd& Z = duals_[i];  // the last pass's on this mesh: CG starts from it
  int iterations = 0;
  TargetError e;
  if (s.body.solveDual(qois_[i].load(mesh), Z, iterations))
    e = goalEstimate(s.energy.spr(), s.body.positions(), in.reference, *in.primal, Z, qois_[i], mesh);
  e.dual_iterations = iterations;
  // After a brain shift the estimate is of the change since; the shift's own error adds
  // (errors add, so do their bounds); with target_shift, that of the scaled problem
  // (underPrescribedShift).
  const VecX* ref = in.reference;
  if (e.valid && ref && i < static_cast<int>(shift_errors_.size()) && shift_errors_[i].valid) {
    e.estimate += shift_errors_[i].estimate;
    e.component_bound += shift_errors_[i].component_bound;
    e.bound += shift_errors_[i].bound;
    e.global_component_bound += shift_errors_[i].global_component_bound;
    e.global_bound += shift_errors_[i].global_bound;
  }
  if (e.valid && ref && i < static_cast<int>(shift_errors_.size())) e.qoi += shift_errors_[i].qoi;
  errors_[i] = std::move(e);
  steps_[i] = s.step;
  errors_step_ = s.step;
  last_step_ = s.step;
  ever_ = true;
  return errors_[i];
}

TargetErrorEstimator::Estimated TargetErrorEstimator::estimated(const TargetErrorState& s) {
  // The field the estimate is of: the change since the brain shift when there was one (the
  // insertion's), else the displacement from rest. On an adaptive mesh that is also the SPR
  // estimate's reference; on a uniform one the primal estimate is made for it here.
  const VecX* reference = s.energy.reference();
  const VecX* ref = reference ? reference : s.shifted;
  const ErrorEstimate* primal = &s.energy.localErrors();  // (and the fits for this mesh)
  if (ref && ref != reference) {
    if (goal_primal_step_ != s.step) {
      goal_primal_ = s.energy.spr().estimate(s.body.positions(), ref);
      goal_primal_step_ = s.step;
    }
    primal = &goal_primal_;
  }
  return {ref, primal};
}

TargetError TargetErrorEstimator::underPrescribedShift(int i, int t, const TargetErrorState& s, const Vec3& d) {
  const TargetError et = of(t, s);
  const TargetError& ei = of(i, s);
  if (!ei.valid || !et.valid) return ei;
  const double along = d.dot(et.qoi);
  if (!(std::abs(along) > 0)) return ei;
  const Estimated in = estimated(s);
  const Eigen::MatrixXd Z = duals_[i] - (duals_[t] * d) * (ei.qoi.transpose() / along);
  TargetError e = goalEstimate(s.energy.spr(), s.body.positions(), in.reference, *in.primal, Z, qois_[i], s.body.mesh());
  e.dual_iterations = ei.dual_iterations;
  return e;
}

const std::vector<TargetError>& TargetErrorEstimator::all(const TargetErrorState& s) {
  for (int i = 0; i < s.points.numTargets(); ++i) of(i, s);
  return errors_;
}

const ErrorEstimate& GoalErrorEstimator::localErrors() {
  const ErrorEstimate& est = energy_.localErrors();
  goal_ = ErrorEstimate{};
  goal_.eta.assign(est.eta.size(), 0.0);
  refine_ = false;
  for (int t : targets_) {
    const TargetError& e = target_error_(t);
    if (!e.valid) {
      refine_ = true;  // no estimate: fall back on the energy estimate's pattern
      for (size_t k = 0; k < goal_.eta.size(); ++k) goal_.eta[k] += est.eta[k] / std::max(est.max, 1e-300);
      continue;
    }
    refine_ = refine_ || e.bound > tolerance_;
    for (size_t k = 0; k < goal_.eta.size(); ++k) goal_.eta[k] += e.indicator[k] / tolerance_;
  }
  double sum = 0;
  for (double v : goal_.eta) {
    goal_.max = std::max(goal_.max, v);
    sum += v * v;
  }
  goal_.global = std::sqrt(sum);
  return goal_;
}

}  // namespace needle_sim

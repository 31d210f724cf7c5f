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
  factor_step_ = -1;
  steps_.assign(steps_.size(), -1);
}

void TargetErrorEstimator::targetsChanged() {
  qois_.clear();
  steps_.assign(steps_.size(), -1);
}

const TargetQoi& TargetErrorEstimator::qoi(int i, const TargetErrorState& s) {
  const size_t n = s.points.numTargets();
  if (qois_.size() != n) {
    const PointLocator locator(s.body.mesh());
    qois_.clear();
    for (int k = 0; k < static_cast<int>(n); ++k)
      qois_.push_back(targetQoi(s.body.mesh(), locator, s.points.target(k).planned, radius(k, s.points)));
  }
  return qois_[static_cast<size_t>(i)];
}

TargetError targetEstimate(const SprEstimator& spr, const VecX& x, const VecX* reference, const ErrorEstimate& primal,
                           const Eigen::MatrixXd& Z, const TargetQoi& qoi, const HexMesh& mesh, const TargetError* shift) {
  TargetError e = goalEstimate(spr, x, reference, primal, Z, qoi, mesh);
  // After a brain shift the estimate is of the change since; the shift's own error adds
  // (errors add, so do their bounds); with target_shift, that of the scaled problem
  // (underPrescribedShift).
  if (!reference || !shift) return e;
  if (shift->valid) {
    e.estimate += shift->estimate;
    e.component_bound += shift->component_bound;
    e.bound += shift->bound;
    e.global_component_bound += shift->global_component_bound;
    e.global_bound += shift->global_bound;
  }
  e.qoi += shift->qoi;
  return e;
}

const TargetError& TargetErrorEstimator::of(int i, const TargetErrorState& s) {
  const size_t n = s.points.numTargets();
  if (errors_.size() != n || steps_.size() != n) {
    errors_.resize(n);
    steps_.resize(n, -1);
  }
  if (steps_[i] == s.step && errors_step_ != -1) return errors_[i];
  const HexMesh& mesh = s.body.mesh();
  const TargetQoi& q = qoi(i, s);
  const Estimated in = estimated(s);
  if (duals_.size() != n) duals_.resize(n);
  // One factor of the stiffness a step, for every target asked for there.
  StiffnessFactor& factor = s.body.dualFactor();
  bool factored = factor_step_ == s.step && factor_x_.size() == s.body.positions().size() &&
                  factor_x_ == s.body.positions();
  if (!factored) {
    factored = factor.factorAt(s.body.positions(), s.body.model().rotationGuesses(), s.body.support());
    factor_step_ = factored ? s.step : -1;
    factor_x_ = s.body.positions();
  }
  Eigen::MatrixXd& Z = duals_[i];
  TargetError e;
  if (factored && factor.solve(q.load(mesh), Z))
    e = targetEstimate(s.energy.spr(), s.body.positions(), in.reference, *in.primal, Z, q, mesh, shiftError(i));
  errors_[i] = std::move(e);
  steps_[i] = s.step;
  errors_step_ = s.step;
  last_step_ = s.step;
  ever_ = true;
  return errors_[i];
}

void TargetErrorEstimator::adopt(int i, TargetError e, long step) {
  if (errors_.size() <= static_cast<size_t>(i)) {
    errors_.resize(static_cast<size_t>(i) + 1);
    steps_.resize(static_cast<size_t>(i) + 1, -1);
  }
  errors_[static_cast<size_t>(i)] = std::move(e);
  steps_[static_cast<size_t>(i)] = -1;  // of an earlier step: not this step's cache
  last_step_ = step;
  ever_ = true;
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
  return goalEstimate(s.energy.spr(), s.body.positions(), in.reference, *in.primal, Z, qois_[i], s.body.mesh());
}

const std::vector<TargetError>& TargetErrorEstimator::all(const TargetErrorState& s) {
  for (int i = 0; i < s.points.numTargets(); ++i) of(i, s);
  return errors_;
}

ErrorEstimate goalIndicators(const ErrorEstimate& est, const std::vector<const TargetError*>& targets,
                             double tolerance, bool& refine) {
  ErrorEstimate goal;
  goal.eta.assign(est.eta.size(), 0.0);
  refine = false;
  for (const TargetError* e : targets) {
    if (!e || !e->valid) {
      refine = true;  // no estimate: fall back on the energy estimate's pattern
      for (size_t k = 0; k < goal.eta.size(); ++k) goal.eta[k] += est.eta[k] / std::max(est.max, 1e-300);
      continue;
    }
    refine = refine || e->bound > tolerance;
    for (size_t k = 0; k < goal.eta.size(); ++k) goal.eta[k] += e->indicator[k] / tolerance;
  }
  double sum = 0;
  for (double v : goal.eta) {
    goal.max = std::max(goal.max, v);
    sum += v * v;
  }
  goal.global = std::sqrt(sum);
  return goal;
}

const ErrorEstimate& GoalErrorEstimator::localErrors() {
  const ErrorEstimate& est = energy_.localErrors();
  std::vector<const TargetError*> errors;
  for (int t : targets_) errors.push_back(&target_error_(t));
  goal_ = goalIndicators(est, errors, tolerance_, refine_);
  return goal_;
}

GoalPass::GoalPass(TargetErrorEstimator& estimator, const TargetErrorState& s, std::vector<int> targets,
                   double tolerance)
    : targets_(std::move(targets)),
      reference_(s.energy.reference() ? s.energy.reference() : s.shifted),
      own_primal_(reference_ != s.energy.reference()),
      support_(s.body.support()),
      mesh_(s.body.mesh()),
      factor_(s.body.backgroundStiffnessFactor()),
      tolerance_(tolerance),
      step_(s.step) {
  for (int t : targets_) {
    qois_.push_back(estimator.qoi(t, s));
    const TargetError* sh = estimator.shiftError(t);
    shift_.push_back(sh ? *sh : TargetError{});
    has_shift_.push_back(sh != nullptr);
  }
}

const ErrorEstimate& GoalPass::run(const SprEstimator& spr, const VecX& x, const std::vector<Eigen::Quaterniond>& guesses,
                                   const ErrorEstimate& energy) {
  // As TargetErrorEstimator::of() and GoalErrorEstimator::localErrors() at the pass's step.
  ErrorEstimate own;
  if (own_primal_) own = spr.estimate(x, reference_, &guesses);
  const ErrorEstimate& primal = own_primal_ ? own : energy;
  errors_.assign(targets_.size(), TargetError{});
  const bool factored = factor_.factorAt(x, guesses, support_);
  Eigen::MatrixXd Z;
  for (size_t k = 0; k < targets_.size(); ++k)
    if (factored && factor_.solve(qois_[k].load(mesh_), Z))
      errors_[k] = targetEstimate(spr, x, reference_, primal, Z, qois_[k], mesh_, has_shift_[k] ? &shift_[k] : nullptr);
  std::vector<const TargetError*> errors;
  for (const TargetError& e : errors_) errors.push_back(&e);
  indicators_ = goalIndicators(energy, errors, tolerance_, refine_);
  return indicators_;
}

void GoalPass::adoptInto(TargetErrorEstimator& estimator) const {
  for (size_t k = 0; k < targets_.size(); ++k) estimator.adopt(targets_[k], errors_[k], step_);
}

}  // namespace needle_sim

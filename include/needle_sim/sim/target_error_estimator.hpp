#pragma once
// The goal-oriented estimates of the targets' displacement errors (adapt/goal_estimator.hpp;
// doc/method.md, "Error on target motion"), one per target, with what they reuse: each
// target's regularised point and last dual solution on the mesh in use (CG's initial guess),
// and the brain shift's own error, which the insertion's estimates add to theirs.
// GoalErrorEstimator turns the controlled targets' element indicators into the marking
// indicators of goal-oriented adaptivity (adapt/error_estimator.hpp).
#include <functional>
#include <vector>

#include "needle_sim/adapt/error_estimator.hpp"
#include "needle_sim/adapt/goal_estimator.hpp"
#include "needle_sim/sim/tracked_points.hpp"
#include "needle_sim/tissue/tissue_body.hpp"

namespace needle_sim {

// What the estimates are of, at the step asked.
struct TargetErrorState {
  const TissueBody& body;
  EnergyErrorEstimator& energy;  // the primal estimate and the SPR fits
  const VecX* shifted;           // the brain-shifted state, or nullptr
  const TrackedPoints& points;
  long step;
};

class TargetErrorEstimator {
 public:
  // default_radius: the regularised point's radius where the scene gives none [m].
  explicit TargetErrorEstimator(double default_radius) : default_radius_(default_radius) {}
  // A copy for a copy of the simulation: the last estimates kept (none current), no duals.
  TargetErrorEstimator(const TargetErrorEstimator& other);
  TargetErrorEstimator& operator=(const TargetErrorEstimator&) = delete;

  // Target i's estimate of the state `s` describes, computed on first use at each step (one
  // 3-column dual solve with the body's current factor and three SPR recoveries). After a
  // brain shift it is the change since the shift plus the shift's own error (errors add, so
  // do their bounds).
  const TargetError& of(int i, const TargetErrorState& s);
  const std::vector<TargetError>& all(const TargetErrorState& s);
  // Target i's error at the state `s` (no shift error added) when the load is scaled to
  // prescribe the length of target t's displacement along the unit direction d
  // (brain_shift.target_shift). To first order the scale's relative error is
  // -d.e_t / d.Q_t(u_h), so the error of Q_i is that of the functional
  //     J_i(u) = Q_i(u) - Q_i(u_h) d.Q_t(u) / d.Q_t(u_h),
  // whose dual is Z_i - Z_t d Q_i(u_h)^T / d.Q_t(u_h): for i = t, the error across d.
  TargetError underPrescribedShift(int i, int t, const TargetErrorState& s, const Vec3& d);
  // The mesh changed: regularised points and duals are made again.
  void forget();
  // A target was added or moved: its regularised point is made again.
  void targetsChanged();
  // The brain shift's own error per target (kept from the end of the pre-step); until the
  // next estimate, also the last ones.
  void setShiftErrors(std::vector<TargetError> errors) {
    shift_errors_ = errors;
    errors_ = std::move(errors);
    ever_ = true;
  }
  // The last estimates computed, and the step they are of, or nullptr / -1.
  const std::vector<TargetError>* last() const { return ever_ ? &errors_ : nullptr; }
  long lastStep() const { return last_step_; }
  // Radius of target i's regularised point [m].
  double radius(int i, const TrackedPoints& points) const { return points.radius(i, default_radius_); }

 private:
  // What the estimate is of at `s`: the reference state (nullptr: rest) and its primal estimate.
  struct Estimated {
    const VecX* reference;
    const ErrorEstimate* primal;
  };
  Estimated estimated(const TargetErrorState& s);

  double default_radius_;
  std::vector<TargetQoi> qois_;            // per target, on the mesh in use (empty: to be made)
  std::vector<Eigen::MatrixXd> duals_;     // per target, the last duals on this mesh
  std::vector<TargetError> errors_;
  std::vector<long> steps_;                // per target: the step its estimate is of
  long errors_step_ = -1;                  // -1: none since the last forget()
  bool ever_ = false;
  long last_step_ = -1;
  ErrorEstimate goal_primal_;              // the primal estimate against the shifted state (uniform meshes)
  long goal_primal_step_ = -1;
  std::vector<TargetError> shift_errors_;  // the brain shift's, per target (empty: none)
};

// Goal-oriented marking: the controlled targets' element indicators, each relative to the
// tolerance; refinement only while a target's bound is above it. A target whose estimate
// failed contributes the energy estimate's pattern instead.
class GoalErrorEstimator : public ErrorEstimator {
 public:
  GoalErrorEstimator(EnergyErrorEstimator& energy, std::function<const TargetError&(int)> target_error,
                     std::vector<int> targets, double tolerance)
      : energy_(energy), target_error_(std::move(target_error)), targets_(std::move(targets)), tolerance_(tolerance) {}
  const ErrorEstimate& localErrors() override;
  bool refinementWanted() override { return refine_; }
  void reset() override {}  // (its inputs are cached where they are computed)

 private:
  EnergyErrorEstimator& energy_;
  std::function<const TargetError&(int)> target_error_;
  std::vector<int> targets_;
  double tolerance_;
  ErrorEstimate goal_;
  bool refine_ = true;
};

}  // namespace needle_sim

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
  // 3-column dual solve with a factor of the stiffness at the step's positions, made once a
  // step for all targets, and three SPR recoveries). After a
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
  // Target i's regularised point on the mesh of `s` (made on first use).
  const TargetQoi& qoi(int i, const TargetErrorState& s);
  // The brain shift's own error of target i, or nullptr.
  const TargetError* shiftError(int i) const {
    return i < static_cast<int>(shift_errors_.size()) ? &shift_errors_[static_cast<size_t>(i)] : nullptr;
  }
  // An estimate of target i at `step` made elsewhere (a goal-oriented pass off the stepping
  // thread, GoalPass) becomes the last one; the next of() at a later step estimates anew.
  void adopt(int i, TargetError e, long step);

 private:
  // What the estimate is of at `s`: the reference state (nullptr: rest) and its primal estimate.
  struct Estimated {
    const VecX* reference;
    const ErrorEstimate* primal;
  };
  Estimated estimated(const TargetErrorState& s);

  double default_radius_;
  std::vector<TargetQoi> qois_;            // per target, on the mesh in use (empty: to be made)
  std::vector<TargetError> errors_;
  std::vector<long> steps_;                // per target: the step its estimate is of
  long errors_step_ = -1;                  // -1: none since the last forget()
  bool ever_ = false;
  long last_step_ = -1;
  ErrorEstimate goal_primal_;              // the primal estimate against the shifted state (uniform meshes)
  long goal_primal_step_ = -1;
  std::vector<Eigen::MatrixXd> duals_;     // per target, the duals of the step below (underPrescribedShift)
  long factor_step_ = -1;                  // the step the body's dual factor was made at (-1: none since forget())
  VecX factor_x_;                          // ... and its positions
  std::vector<TargetError> shift_errors_;  // the brain shift's, per target (empty: none)
};

// Target i's estimate from the dual solutions Z of its regularised point (goalEstimate), plus
// the brain shift's own error when it is of the change since the shift (reference given):
// errors add, so do their bounds. `shift`: the shift's error, or nullptr.
TargetError targetEstimate(const SprEstimator& spr, const VecX& x, const VecX* reference, const ErrorEstimate& primal,
                           const Eigen::MatrixXd& Z, const TargetQoi& qoi, const HexMesh& mesh, const TargetError* shift);

// Goal-oriented marking: the controlled targets' element indicators, each relative to the
// tolerance; refinement only while a target's bound is above it. A target whose estimate
// failed (nullptr or invalid) contributes the energy estimate's pattern instead.
ErrorEstimate goalIndicators(const ErrorEstimate& energy, const std::vector<const TargetError*>& targets,
                             double tolerance, bool& refine);

// A goal-oriented pass off the stepping thread (AdaptationPasses, adaptivity.estimate_delay).
// Made on the stepping thread at the pass's step: copies of what the controlled targets'
// estimates read there (their regularised points, the shift's errors, the support springs)
// and the body's background stiffness factor, lent until the decision. run() on the pass's
// thread gives what GoalErrorEstimator::localErrors() would have at that step, bit for bit;
// adoptInto() at the decision makes its targets' estimates the last ones.
class GoalPass {
 public:
  GoalPass(TargetErrorEstimator& estimator, const TargetErrorState& s, std::vector<int> targets, double tolerance);
  // From the positions x at the pass's step, the rotations' starting points there and the
  // energy estimator's estimate of them (SprEstimator::estimate against its reference).
  const ErrorEstimate& run(const SprEstimator& spr, const VecX& x, const std::vector<Eigen::Quaterniond>& guesses,
                           const ErrorEstimate& energy);
  bool refinementWanted() const { return refine_; }
  const std::vector<TargetError>& errors() const { return errors_; }
  void adoptInto(TargetErrorEstimator& estimator) const;

 private:
  std::vector<int> targets_;
  std::vector<TargetQoi> qois_;
  std::vector<TargetError> shift_;
  std::vector<char> has_shift_;
  const VecX* reference_;  // the field's (TargetErrorEstimator::estimated)
  bool own_primal_;        // ... not the energy estimate's: a primal estimate of its own
  ElementBlocks support_;
  const HexMesh& mesh_;
  StiffnessFactor& factor_;
  double tolerance_;
  long step_;
  std::vector<TargetError> errors_;
  ErrorEstimate indicators_;
  bool refine_ = true;
};

// Goal-oriented marking on the stepping thread (goalIndicators of the targets' estimates now).
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

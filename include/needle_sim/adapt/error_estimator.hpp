#pragma once
// What drives an adaptation pass: element error indicators of the current state (MFEM's
// ErrorEstimator: GetLocalErrors and Reset). Two estimators implement it: the SPR energy-norm
// estimate (EnergyErrorEstimator, below) and the goal-oriented indicators of chosen targets
// (GoalErrorEstimator, sim/target_error_estimator.hpp); MeshAdaptation::adapt marks with either.
// An estimator computes on first use after reset() and keeps its result until the next one.
#include <atomic>
#include <memory>

#include "needle_sim/adapt/spr_estimator.hpp"
#include "needle_sim/tissue/tissue_body.hpp"

namespace needle_sim {

class ErrorEstimator {
 public:
  virtual ~ErrorEstimator() = default;
  // Per-element indicators of the current state (eta, with their max and global norm).
  virtual const ErrorEstimate& localErrors() = 0;
  // False when the estimator's tolerance is met: a pass then only coarsens.
  virtual bool refinementWanted() { return true; }
  // The state changed: the next localErrors() computes anew.
  virtual void reset() = 0;
};

// The SPR estimate of a tissue body's state (spr_estimator.hpp): of the displacement from
// rest, or of the change since a reference state when `reference` is non-empty (the shifted
// brain: the change the insertion makes). The SPR fits belong to the body's mesh: made on
// first use, or handed over with a body built in the background (rebind).
//
// Threading: an adaptation pass on a background thread (AdaptationPasses) estimates with
// spr() while the stepping thread steps on; from lend() to giveBack() the stepping thread
// must not estimate (localErrors throws std::logic_error then: a broken wait protocol).
class EnergyErrorEstimator : public ErrorEstimator {
 public:
  EnergyErrorEstimator(const TissueBody* body, const VecX* reference) : body_(body), reference_(reference) {}
  // For a copy of the body: the last estimate kept (not current), the fits made again.
  EnergyErrorEstimator(const EnergyErrorEstimator& other, const TissueBody* body, const VecX* reference);
  EnergyErrorEstimator(const EnergyErrorEstimator&) = delete;
  EnergyErrorEstimator& operator=(const EnergyErrorEstimator&) = delete;

  const ErrorEstimate& localErrors() override;
  void reset() override { current_ = false; }

  // A new body (a mesh change): the fits made with it, or none (made on first use).
  void rebind(const TissueBody* body, std::unique_ptr<SprEstimator> fits = nullptr);
  // The fits of the body's mesh (made now if need be).
  const SprEstimator& spr();
  // The state the estimate measures the change from, or nullptr.
  const VecX* reference() const { return reference_ && reference_->size() ? reference_ : nullptr; }
  // An estimate made elsewhere (a background pass's, of an earlier step) becomes the last one.
  void adopt(ErrorEstimate estimate);
  // The last estimate computed or adopted, or nullptr; the current state's, or nullptr.
  const ErrorEstimate* last() const { return ever_ ? &estimate_ : nullptr; }
  const ErrorEstimate* current() const { return current_ ? &estimate_ : nullptr; }

  void lend() { lent_ = true; }
  void giveBack() { lent_ = false; }

 private:
  const TissueBody* body_;
  const VecX* reference_;
  std::unique_ptr<SprEstimator> spr_;
  ErrorEstimate estimate_;
  bool current_ = false, ever_ = false;
  std::atomic<bool> lent_{false};
};

}  // namespace needle_sim

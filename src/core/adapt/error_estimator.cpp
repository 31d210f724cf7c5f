#include "needle_sim/adapt/error_estimator.hpp"

#include <stdexcept>

namespace needle_sim {

EnergyErrorEstimator::EnergyErrorEstimator(const EnergyErrorEstimator& o, const TissueBody* body, const VecX* reference)
    : body_(body), reference_(reference), estimate_(o.estimate_), current_(false), ever_(o.ever_) {}

const ErrorEstimate& EnergyErrorEstimator::localErrors() {
  if (!current_) {
    if (lent_) throw std::logic_error("EnergyErrorEstimator: estimate asked for while a background pass holds the fits");
    ever_ = true;
    estimate_ = spr().estimate(body_->positions(), reference());
    current_ = true;
  }
  return estimate_;
}

void EnergyErrorEstimator::rebind(const TissueBody* body, std::unique_ptr<SprEstimator> fits) {
  body_ = body;
  spr_ = std::move(fits);
  current_ = false;
}

const SprEstimator& EnergyErrorEstimator::spr() {
  if (!spr_) spr_ = std::make_unique<SprEstimator>(body_->model());
  return *spr_;
}

void EnergyErrorEstimator::adopt(ErrorEstimate estimate) {
  estimate_ = std::move(estimate);
  ever_ = true;
}

}  // namespace needle_sim

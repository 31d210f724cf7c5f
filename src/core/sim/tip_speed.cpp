#include "needle_sim/sim/tip_speed.hpp"

#include "needle_sim/sim/simulation.hpp"

namespace needle_sim {

void TipSpeedMeter::reset() {
  tips_.clear();
  t_ = std::numeric_limits<double>::quiet_NaN();
  speed_.assign(speed_.size(), 0.0);
  largest_.assign(largest_.size(), 0.0);
  largest_at_.assign(largest_at_.size(), 0.0);
}

void TipSpeedMeter::observe(const Simulation& sim) {
  const int n = sim.numNeedles();
  const double t = sim.time();
  if (static_cast<int>(speed_.size()) != n) {
    speed_.assign(n, 0.0);
    largest_.assign(n, 0.0);
    largest_at_.assign(n, 0.0);
    tips_.clear();
  }
  const bool measured = static_cast<int>(tips_.size()) == n && t > t_;
  if (static_cast<int>(tips_.size()) != n) tips_.resize(n);
  for (int i = 0; i < n; ++i) {
    const Vec3 tip = sim.needle(i).tipPosition();
    if (measured) {
      speed_[i] = (tip - tips_[i]).norm() / (t - t_);
      if (speed_[i] > largest_[i]) {
        largest_[i] = speed_[i];
        largest_at_[i] = t;
      }
    } else {
      speed_[i] = 0;
    }
    tips_[i] = tip;
  }
  t_ = t;
}

}  // namespace needle_sim

#include "needle_sim/calibration/parameter_adoption.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "needle_sim/sim/simulation.hpp"

namespace needle_sim {

ParameterAdoption::ParameterAdoption(std::vector<std::string> keys, double ramp) : keys_(std::move(keys)), ramp_(ramp) {
  if (!(ramp >= 0) || !std::isfinite(ramp)) throw std::invalid_argument("ParameterAdoption: the ramp must be finite and >= 0");
  for (const std::string& k : keys_) adoptable_.push_back(Simulation::adoptable(k));
}

void ParameterAdoption::target(const Simulation& sim, const std::vector<double>& values) {
  if (values.size() != keys_.size()) throw std::invalid_argument("ParameterAdoption::target: a value per key");
  const double t = sim.time();
  for (size_t k = 0; k < keys_.size(); ++k) {
    if (!adoptable_[k] || !std::isfinite(values[k])) continue;
    auto it = std::find_if(ramps_.begin(), ramps_.end(), [&](const Entry& e) { return e.key == keys_[k]; });
    if (it != ramps_.end()) ramps_.erase(it);
    // From the value in use (a ramp under way: where it has got to).
    ramps_.push_back({keys_[k], sim.valueInUse(keys_[k]), values[k], t, t + ramp_});
  }
}

void ParameterAdoption::apply(Simulation& sim) {
  const double t = sim.time();
  for (auto it = ramps_.begin(); it != ramps_.end();) {
    // The share of the ramp done by the end of the next step: the value it steps with.
    const double next = t + sim.dt();
    const double s = it->t1 > it->t0 ? std::clamp((next - it->t0) / (it->t1 - it->t0), 0.0, 1.0) : 1.0;
    sim.adopt(it->key, it->from + s * (it->to - it->from));
    it = s >= 1 ? ramps_.erase(it) : it + 1;
  }
}

}  // namespace needle_sim

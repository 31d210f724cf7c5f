#pragma once
// The live simulation taking estimated values during a run (issue #41; doc/ros_api.md,
// "Assimilation"): each adoptable key (Simulation::adoptable) moves from its value in use to
// the estimate linearly over `ramp` seconds of simulation time, so that the force the
// simulation reports changes by the whole change's share dt / ramp a step, not at once.
// A new estimate during a ramp starts a new one from where the value is.
#include <string>
#include <vector>

namespace needle_sim {

class Simulation;

class ParameterAdoption {
 public:
  // keys: the estimated keys (those that are not adoptable are left alone: adoptable()).
  // ramp [s] >= 0 (0: at once).
  ParameterAdoption(std::vector<std::string> keys, double ramp);

  bool adoptable(int k) const { return adoptable_[k]; }
  // An estimate (a value per key; a non-finite one is not adopted) at the simulation's time.
  void target(const Simulation& sim, const std::vector<double>& values);
  // After a step: the values due at the simulation's time, set in it (Simulation::adopt).
  void apply(Simulation& sim);
  bool ramping() const { return !ramps_.empty(); }
  // The adoptable keys' values in use and where they head.
  struct Entry {
    std::string key;
    double from, to, t0, t1;
  };
  const std::vector<Entry>& ramps() const { return ramps_; }

 private:
  std::vector<std::string> keys_;
  std::vector<bool> adoptable_;
  double ramp_;
  std::vector<Entry> ramps_;  // under way
};

}  // namespace needle_sim

#pragma once
// The speed of each needle's tip, measured every step from the needle states: the command
// guard limits the base, not the tip, and a needle bent inside the tissue can snap sideways
// when it leaves it (issue #39: 9.5 mm in a few steps, 1.6 m/s over one step, with the base
// at 0.05 m/s). The node warns above ~max_tip_speed; ~predict, ~insert and `needle_sim
// predict` report the largest, so a planner sees a snap-back before it sends the command.
// The speed is the tip's displacement over one step divided by the step (a step-to-step
// figure: at a coarser time step the same snap reads slower). Cost: a subtraction and a
// norm per needle and step.
#include <limits>
#include <vector>

#include "needle_sim/core/types.hpp"

namespace needle_sim {

class Simulation;

class TipSpeedMeter {
 public:
  // After each step (and once before the first: it only records the tips then). A call at
  // the same time as the last one, or earlier (a reset), measures nothing and starts again.
  void observe(const Simulation& sim);
  // Forget the tips: the next observe() measures nothing (a reset, a restored state).
  void reset();
  int numNeedles() const { return static_cast<int>(speed_.size()); }
  // Of the last step [m/s] (0 before a step was measured).
  double speed(int n) const { return speed_[n]; }
  // The largest since the start or the last reset [m/s], and the time it was measured at.
  double largest(int n) const { return largest_[n]; }
  double largestAt(int n) const { return largest_at_[n]; }

 private:
  std::vector<Vec3> tips_;
  double t_ = std::numeric_limits<double>::quiet_NaN();
  std::vector<double> speed_, largest_, largest_at_;
};

}  // namespace needle_sim

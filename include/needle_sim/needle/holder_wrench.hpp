#pragma once
// The force and moment a needle exerts on its holder between two steps of the simulation, for
// a consumer faster than the step (a 1 kHz force controller on a 10 ms scene; doc/method.md,
// "The holder's wrench between steps"). The local model is frozen over the step: the last
// step's change of the wrench per base displacement along the base's last motion (a secant),
// times the base's displacement since the step along that motion. Held instead when the last
// step changed the needle's constraint points (a shaft point laid, a puncture, a release: an
// event's jump, not the motion's) or the base did not move. At a step it is the step's value.
#include "needle_sim/core/types.hpp"

namespace needle_sim {

class HolderWrenchExtrapolation {
 public:
  // After a step: the base position the step ended at, the wrench on the holder (one frame
  // throughout) and the needle's number of constraint points.
  void afterStep(const Vec3& base, const Vec3& force, const Vec3& moment, int constraint_points);
  // Until the next step: the wrench with the base at `base`.
  void at(const Vec3& base, Vec3& force, Vec3& moment) const;
  // Whether the last step gave a slope (otherwise at() holds the step's wrench).
  bool extrapolates() const { return slope_; }

 private:
  bool stepped_ = false, slope_ = false;
  int points_ = 0;
  Vec3 base_ = Vec3::Zero(), force_ = Vec3::Zero(), moment_ = Vec3::Zero();
  Vec3 motion_ = Vec3::Zero(), dforce_ = Vec3::Zero(), dmoment_ = Vec3::Zero();  // over the last step
};

}  // namespace needle_sim

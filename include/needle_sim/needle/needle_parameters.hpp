#pragma once
// What a needle body needs to know (a scene's `needle` or `needles[i]` entry): the beam,
// its base pose at rest, its prescribed base motion, loads.
#include <string>
#include <vector>

#include "needle_sim/core/types.hpp"

namespace needle_sim {

struct NeedleMotionKey {
  double t = 0;
  Vec3 position = Vec3::Zero();
  Vec3 direction = Vec3::UnitX();
  double roll = 0;
  // Duty-cycled spinning over the segment from this key to the next (Minhas et al. 2007;
  // needle/duty_cycled_spin.hpp): a fraction spin_duty of the segment's time spent turning
  // at spin_rate [rad/s], in whole turns. 0: no spinning.
  double spin_rate = 0;
  double spin_duty = 0;
};

// A needle (or cannula, electrode): a corotational beam whose base follows `motion`.
struct NeedleParameters {
  std::string name = "needle";
  double length = 0.1;
  double radius = 1e-3;
  double inner_radius = 0.0;
  double young = 2e11, poisson = 0.3, density = 8000;
  int elements = 20;
  Vec3 base_position = Vec3::Zero();
  Vec3 base_direction = Vec3::UnitX();
  double base_roll = 0;
  std::vector<NeedleMotionKey> motion;  // strictly increasing t
  Vec3 tip_force = Vec3::Zero();        // external load at the tip [N], e.g. for verification
  Vec3 tip_moment = Vec3::Zero();       // [N m]
  Vec3 gravity = Vec3::Zero();          // [m/s^2]
};

}  // namespace needle_sim

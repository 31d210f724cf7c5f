#pragma once
// What a needle body needs to know (a scene's `needle` or `needles[i]` entry): the beam,
// its base pose at rest, its prescribed base motion, loads.
#include <cmath>
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

// A bevel tip (doc/method.md "Bevel tip"). While the tip cuts, the tissue pushes it sideways
// with lateral_ratio times the cutting strength (interaction.cutting_force), along the
// bevel direction: the tip frame's y axis turned by `orientation` about its x axis (the
// needle axis; frames in the pose convention, command/pose_convention.hpp), i.e. towards
// the bevel's sharp point, the side a bevel-tipped needle bends to.
struct BevelParameters {
  bool enabled = false;
  double angle = 0;          // between the bevel face and the needle axis, (0, pi/2) [rad]
  double lateral_ratio = 0;  // lateral load / cutting strength (>= 0); the scene's default: bevelLateralRatio
  double orientation = 0;    // [rad]
};

// The lateral-to-axial load ratio of a bevel face at `angle` to the axis cutting with face
// friction mu: the face carries a pressure normal to it and a friction along it,
// whose lateral and axial components give Q / P = (cos a - mu sin a) / (sin a + mu cos a)
// (doc/method.md "Bevel tip" for the source and the range). Clamped at 0 (a blunt, rough face
// pushes no sideways).
inline double bevelLateralRatio(double angle, double mu) {
  const double q = (std::cos(angle) - mu * std::sin(angle)) / (std::sin(angle) + mu * std::cos(angle));
  return q > 0 ? q : 0.0;
}

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
  BevelParameters bevel;
};

}  // namespace needle_sim

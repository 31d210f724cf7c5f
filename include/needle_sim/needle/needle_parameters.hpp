#pragma once
// What a needle body needs to know (a scene's `needle` or `needles[i]` entry): the beam,
// its base pose at rest, its prescribed base motion, loads.
#include <cmath>
#include <string>
#include <vector>

#include "needle_sim/core/parameters.hpp"
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

  // The `bevel` keys of a needle (core/parameters.hpp); a needle has a bevel when it has them.
  static const Parameters<BevelParameters>& parameters() {
    using S = BevelParameters;
    static const Parameters<S> p =
        Parameters<S>()
            .real("angle", [](S& s) -> double& { return s.angle; }, "rad", Range::open(0, M_PI / 2),
                  "angle between the bevel face and the needle axis; a `bevel` map needs it", true)
            .real("lateral_ratio", [](S& s) -> double& { return s.lateral_ratio; }, "", Range::nonNegative(),
                  "the tip's lateral load while it cuts, as a multiple of `interaction.cutting_force`; default (cos a − μ sin a)/(sin a + μ cos a), clamped at 0 (a the angle, μ = `interaction.friction`)")
            .real("orientation", [](S& s) -> double& { return s.orientation; }, "rad", Range::any(),
                  "the bevel's lateral direction in the tip frame: its y axis turned by this about the needle axis");
    return p;
  }
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

  // A needle entry's value keys (core/parameters.hpp); base.direction (a unit vector), the
  // motion and the bevel are read by the scene loader.
  static const Parameters<NeedleParameters>& parameters() {
    using S = NeedleParameters;
    static const Parameters<S> p =
        Parameters<S>()
            .text("name", [](S& s) -> std::string& { return s.name; },
                  "`[A-Za-z0-9_]+`, unique; required in `needles` (it names CSV columns and ROS topics)")
            .real("length", [](S& s) -> double& { return s.length; }, "m", Range::positive(), "from base to tip", true)
            .real("radius", [](S& s) -> double& { return s.radius; }, "m", Range::positive(), "outer radius", true)
            .real("inner_radius", [](S& s) -> double& { return s.inner_radius; }, "m", Range::nonNegative(),
                  "a tube (cannula): 0 ≤ inner_radius < radius")
            .real("young", [](S& s) -> double& { return s.young; }, "Pa", Range::positive(), "Young's modulus", true)
            .real("poisson", [](S& s) -> double& { return s.poisson; }, "", Range::open(-1, 0.5), "Poisson's ratio", true)
            .real("density", [](S& s) -> double& { return s.density; }, "kg/m^3", Range::positive(), "mass density", true)
            .integer("elements", [](S& s) -> int& { return s.elements; }, Range::closed(1, 100000),
                     "beam elements", true)
            .vector("base.position", [](S& s) -> Vec3& { return s.base_position; }, "m",
                    "base node at rest", true)
            .real("base.roll", [](S& s) -> double& { return s.base_roll; }, "rad", Range::any(),
                  "twist of the rest frame about the axis")
            .vector("tip_force", [](S& s) -> Vec3& { return s.tip_force; }, "N", "external load at the tip (verification)")
            .vector("tip_moment", [](S& s) -> Vec3& { return s.tip_moment; }, "N m", "external moment at the tip")
            .vector("gravity", [](S& s) -> Vec3& { return s.gravity; }, "m/s^2", "gravitational acceleration on the needle");
    return p;
  }
};

}  // namespace needle_sim

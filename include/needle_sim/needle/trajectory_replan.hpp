#pragma once
// Intraoperative re-planning (doc/method.md, "Brain shift"): after the brain has shifted, the
// surgeon re-aims the trajectory at the target's new position through the same entry point
// (the burr hole). A needle's planned base motion is re-aimed by the similarity about its
// entry point E (where its tip is at rest) that carries its planned final tip P (the deepest
// keyframe's tip: a cannula is withdrawn afterwards) to P + shift:
// the rotation R from P - E to P + shift - E and the scale k = |P + shift - E| / |P - E|.
// Every keyframe's tip point T goes to E + k R (T - E) and its axis d to R d, so a straight
// insertion through E stays straight through E, its advance scaled by k; needles sharing an
// axis and an entry point (cannula and electrode) stay coaxial.
//
// Aiming a tool anew (rigidAim: `needle_sim check --aim`, the ensemble's trajectories): the
// needles of one tool (cannula and electrode) moved rigidly, as one body, so that the
// reference needle's planned final tip (the same rule: its deepest keyframe's tip) goes to a
// target and its rest axis to the direction entry -> target.
#include <Eigen/Geometry>

#include "needle_sim/needle/needle_parameters.hpp"

namespace needle_sim {

// A needle's planned final tip: the tip of its deepest keyframe, the one farthest from its tip
// at rest (a cannula is withdrawn after it); the tip at rest when it has no motion. The one
// rule of replanFor and rigidAim.
struct PlannedTip {
  Vec3 rest_tip = Vec3::Zero();  // E: base + length x axis at rest
  Vec3 tip = Vec3::Zero();       // P
  int keyframe = -1;             // its motion keyframe; -1: no motion (P = E)
};
PlannedTip plannedFinalTip(const NeedleParameters& n);

struct TrajectoryReplan {
  Vec3 entry = Vec3::Zero();                                    // E: the tip at rest
  Vec3 planned_tip = Vec3::Zero();                              // P: the deepest keyframe's tip
  Eigen::Quaterniond rotation = Eigen::Quaterniond::Identity();  // R
  double scale = 1.0;                                           // k
  double angle() const { return 2 * std::atan2(rotation.vec().norm(), std::abs(rotation.w())); }
};

// The re-plan moving needle n's planned final tip by `shift`. A needle without motion keeps
// its plan (identity). Throws std::invalid_argument when no keyframe takes the tip away from
// its entry point (nothing to re-aim).
TrajectoryReplan replanFor(const NeedleParameters& n, const Vec3& shift);

// n with its rest pose and every keyframe re-aimed by r (the rest pose's tip is E itself).
NeedleParameters replanned(const NeedleParameters& n, const TrajectoryReplan& r);

// A rigid motion of a tool, x -> target + R (x - P), d -> R d: R the smallest rotation taking
// the reference needle's rest axis onto target - entry, P its planned final tip.
struct RigidAim {
  Vec3 planned_tip = Vec3::Zero();  // P, of the reference needle
  Vec3 target = Vec3::Zero();
  Eigen::Matrix3d rotation = Eigen::Matrix3d::Identity();  // R
  Vec3 point(const Vec3& x) const { return target + rotation * (x - planned_tip); }
  Vec3 direction(const Vec3& d) const { return rotation * d; }
  double angle() const { return Eigen::AngleAxisd(rotation).angle(); }
};

// The aim that puts `reference`'s planned final tip on `target`, its axis along
// target - entry. Throws std::invalid_argument when entry and target (nearly) coincide.
RigidAim rigidAim(const NeedleParameters& reference, const Vec3& entry, const Vec3& target);

// n moved by a: its rest pose and every keyframe. Directions are turned as given, not
// renormalised, so that a moved needle is the same body rigidly moved: the reference's
// planned final tip lands on the target to rounding.
NeedleParameters rigidlyMoved(const NeedleParameters& n, const RigidAim& a);

}  // namespace needle_sim

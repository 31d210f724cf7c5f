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
#include <Eigen/Geometry>

#include "needle_sim/needle/needle_parameters.hpp"

namespace needle_sim {

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

}  // namespace needle_sim

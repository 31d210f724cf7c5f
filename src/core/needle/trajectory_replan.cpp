#include "needle_sim/needle/trajectory_replan.hpp"

#include <stdexcept>

namespace needle_sim {

TrajectoryReplan replanFor(const NeedleParameters& n, const Vec3& shift) {
  TrajectoryReplan r;
  r.entry = n.base_position + n.length * n.base_direction.normalized();
  if (n.motion.empty()) {
    r.planned_tip = r.entry;
    return r;
  }
  // The planned final tip: the deepest keyframe (a cannula is withdrawn after it).
  double deepest = -1;
  for (const NeedleMotionKey& k : n.motion) {
    const Vec3 tip = k.position + n.length * k.direction.normalized();
    if ((tip - r.entry).norm() > deepest) {
      deepest = (tip - r.entry).norm();
      r.planned_tip = tip;
    }
  }
  const Vec3 from = r.planned_tip - r.entry, to = from + shift;
  if (!(from.norm() > 1e-9 * n.length))
    throw std::invalid_argument("needle '" + n.name + "' never leaves its entry point: no trajectory to re-aim");
  r.rotation = Eigen::Quaterniond::FromTwoVectors(from, to);
  r.scale = to.norm() / from.norm();
  return r;
}

NeedleParameters replanned(const NeedleParameters& n, const TrajectoryReplan& r) {
  NeedleParameters out = n;
  const Eigen::Matrix3d R = r.rotation.toRotationMatrix();
  auto reaim = [&](Vec3& base, Vec3& direction) {
    const Vec3 d = direction.normalized();
    const Vec3 tip = base + n.length * d;
    direction = R * d;
    base = r.entry + r.scale * (R * (tip - r.entry)) - n.length * direction;
  };
  reaim(out.base_position, out.base_direction);
  for (auto& k : out.motion) reaim(k.position, k.direction);
  return out;
}

}  // namespace needle_sim

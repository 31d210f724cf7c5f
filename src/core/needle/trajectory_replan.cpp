#include "needle_sim/needle/trajectory_replan.hpp"

#include <stdexcept>

namespace needle_sim {

PlannedTip plannedFinalTip(const NeedleParameters& n) {
  PlannedTip p;
  p.rest_tip = n.base_position + n.length * n.base_direction.normalized();
  p.tip = p.rest_tip;
  // The deepest keyframe (a cannula is withdrawn after it); the first of equally deep ones.
  double deepest = -1;
  for (size_t i = 0; i < n.motion.size(); ++i) {
    const NeedleMotionKey& k = n.motion[i];
    const Vec3 tip = k.position + n.length * k.direction.normalized();
    if ((tip - p.rest_tip).norm() > deepest) {
      deepest = (tip - p.rest_tip).norm();
      p.tip = tip;
      p.keyframe = static_cast<int>(i);
    }
  }
  return p;
}

TrajectoryReplan replanFor(const NeedleParameters& n, const Vec3& shift) {
  TrajectoryReplan r;
  const PlannedTip p = plannedFinalTip(n);
  r.entry = p.rest_tip;
  r.planned_tip = p.tip;
  if (n.motion.empty()) return r;
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

RigidAim rigidAim(const NeedleParameters& reference, const Vec3& entry, const Vec3& target) {
  const Vec3 axis = target - entry;
  if (!(axis.norm() > 1e-9))
    throw std::invalid_argument("the entry point and the target coincide: no axis to aim along");
  RigidAim a;
  a.planned_tip = plannedFinalTip(reference).tip;
  a.target = target;
  a.rotation = Eigen::Quaterniond::FromTwoVectors(reference.base_direction.normalized(), axis.normalized())
                   .toRotationMatrix();
  return a;
}

NeedleParameters rigidlyMoved(const NeedleParameters& n, const RigidAim& a) {
  NeedleParameters out = n;
  out.base_position = a.point(n.base_position);
  out.base_direction = a.direction(n.base_direction);
  for (auto& k : out.motion) {
    k.position = a.point(k.position);
    k.direction = a.direction(k.direction);
  }
  return out;
}

}  // namespace needle_sim

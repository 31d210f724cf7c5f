#include "needle_sim/command/pose_convention.hpp"

#include <cmath>

#include "needle_sim/needle/needle_body.hpp"

namespace needle_sim {

double wrapAngle(double a) {
  a = std::remainder(a, 2 * M_PI);  // [-pi, pi]
  return a <= -M_PI ? a + 2 * M_PI : a;
}

BasePose basePoseFrom(const Vec3& position, const Eigen::Quaterniond& q, const BasePose& rest, double roll_near) {
  const Vec3 d = (q * Vec3::UnitX()).normalized();
  // Roll: the twist about the axis of q relative to the frame that carries x to the rest
  // axis and then, by the smallest rotation, to d. The rest pose's own frame is that one
  // rolled by rest.roll, so the twist is the roll itself.
  const Eigen::Quaterniond ref =
      Eigen::Quaterniond::FromTwoVectors(rest.direction, d) * Eigen::Quaterniond::FromTwoVectors(Vec3::UnitX(), rest.direction);
  const Eigen::Quaterniond twist = ref.conjugate() * q;
  const double roll = 2 * std::atan2(twist.x(), twist.w());
  BasePose p;
  p.position = position;
  p.direction = d;
  p.roll = roll_near + wrapAngle(roll - roll_near);
  return p;
}

Eigen::Quaterniond orientationOf(const BasePose& p, const BasePose& rest) {
  return (Eigen::Quaterniond::FromTwoVectors(rest.direction, p.direction) *
          Eigen::Quaterniond::FromTwoVectors(Vec3::UnitX(), rest.direction) * Eigen::AngleAxisd(p.roll, Vec3::UnitX()))
      .normalized();
}

Eigen::Quaterniond nodeFrame(const NeedleBody& needle, int node) { return needle.nodeFrame(node); }

}  // namespace needle_sim

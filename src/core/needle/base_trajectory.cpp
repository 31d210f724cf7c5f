#include "needle_sim/needle/base_trajectory.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>

namespace needle_sim {

BaseTrajectory::BaseTrajectory(const BasePose& rest) : rest_(rest) { keys_.push_back({0.0, rest}); }

void BaseTrajectory::add(double t, const BasePose& p) {
  if (!(std::isfinite(t) && p.position.allFinite() && p.direction.allFinite() && std::isfinite(p.roll)))
    throw std::invalid_argument("base command is not finite");
  if (std::abs(p.direction.norm() - 1) > 1e-6) throw std::invalid_argument("base direction is not a unit vector");
  if (keys_.size() == 1 && keys_[0].t == 0.0 && t == 0.0) {
    keys_[0].pose = p;  // a keyframe at t = 0 replaces the implicit one
    return;
  }
  if (!(t > keys_.back().t)) throw std::invalid_argument("base command times must increase");
  keys_.push_back({t, p});
}

BasePose BaseTrajectory::pose(double t) const {
  if (t <= keys_.front().t) return keys_.front().pose;
  if (t >= keys_.back().t) return keys_.back().pose;
  const auto it = std::upper_bound(keys_.begin(), keys_.end(), t, [](double v, const Key& k) { return v < k.t; });
  const Key& b = *it;
  const Key& a = *(it - 1);
  return interpolate(a.pose, b.pose, (t - a.t) / (b.t - a.t));
}

BasePose BaseTrajectory::interpolate(const BasePose& a, const BasePose& b, double s) const {
  BasePose p;
  p.position = (1 - s) * a.position + s * b.position;
  p.roll = (1 - s) * a.roll + s * b.roll;
  const Eigen::Quaterniond qa = Eigen::Quaterniond::FromTwoVectors(rest_.direction, a.direction);
  const Eigen::Quaterniond qb = Eigen::Quaterniond::FromTwoVectors(rest_.direction, b.direction);
  p.direction = (qa.slerp(s, qb) * rest_.direction).normalized();
  return p;
}

Eigen::Quaterniond BaseTrajectory::orientation(const BasePose& p) const {
  const Eigen::Quaterniond align = Eigen::Quaterniond::FromTwoVectors(rest_.direction, p.direction);
  const Eigen::Quaterniond roll(Eigen::AngleAxisd(p.roll - rest_.roll, rest_.direction));
  return (align * roll).normalized();
}

}  // namespace needle_sim

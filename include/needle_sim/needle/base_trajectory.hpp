#pragma once
// The commanded pose of a needle base over time: keyframes (t, position, axis direction,
// roll about the axis) interpolated piecewise-linearly (position, roll) and by slerp
// (direction); held constant before the first and after the last keyframe. The ROS node
// appends commands through add() as they arrive; scene files give them up front.
#include <Eigen/Geometry>
#include <algorithm>
#include <limits>
#include <utility>
#include <vector>

#include "needle_sim/core/types.hpp"

namespace needle_sim {

struct BasePose {
  Vec3 position = Vec3::Zero();
  Vec3 direction = Vec3::UnitX();  // unit needle axis
  double roll = 0.0;               // radians about the axis
};

class BaseTrajectory {
 public:
  // rest: the base pose of the needle's rest configuration, also the pose at t = 0 unless
  // a keyframe says otherwise.
  explicit BaseTrajectory(const BasePose& rest);

  // Appends a keyframe; t must exceed the last keyframe's time (throws std::invalid_argument).
  void add(double t, const BasePose& pose);
  // Replaces the pose of the last keyframe (a later command for the same instant).
  void replaceLast(const BasePose& pose) {
    if (!keys_.empty()) keys_.back().pose = pose;
  }
  // Commanded pose at time t.
  BasePose pose(double t) const;
  // The pose a fraction s in [0, 1] of the way from a to b, as pose(t) interpolates between
  // keyframes: position and roll linearly, the axis by slerp of its rotation from the rest axis.
  BasePose interpolate(const BasePose& a, const BasePose& b, double s) const;
  // Rotation carrying the rest base frame to the commanded one: the minimal rotation from
  // the rest axis to the commanded axis, after a roll about the rest axis.
  Eigen::Quaterniond orientation(const BasePose& p) const;
  const BasePose& rest() const { return rest_; }
  // Drops the keyframes after time t, keeping the pose at t (a new plan starts there).
  void truncateAfter(double t) {
    if (keys_.empty() || keys_.back().t <= t) return;
    const BasePose at = pose(t);
    while (!keys_.empty() && keys_.back().t > t) keys_.pop_back();
    if (keys_.empty() || keys_.back().t < t) keys_.push_back({t, at});
  }
  // A plan from time t0 on: what was commanded after t0 is dropped, the pose at t0 held,
  // then each waypoint (time from t0, pose) is added, none sooner than t0 + min_step (a
  // later waypoint for the same instant replaces the earlier one).
  void replaceFrom(double t0, double min_step, const std::vector<std::pair<double, BasePose>>& waypoints) {
    truncateAfter(t0);
    if (lastTime() < t0) add(t0, pose(t0));
    for (const auto& [dt, p] : waypoints) {
      const double t = std::max(t0 + dt, t0 + min_step);
      if (t > lastTime())
        add(t, p);
      else
        replaceLast(p);
    }
  }
  // Forgets keyframes that no longer matter at times >= t (all but the last one before t),
  // so that a stream of commands does not grow the list without bound.
  void dropBefore(double t) {
    size_t k = 0;
    while (k + 1 < keys_.size() && keys_[k + 1].t <= t) ++k;
    if (k > 0) keys_.erase(keys_.begin(), keys_.begin() + static_cast<long>(k));
  }
  // Keeps what is commanded up to time t and nothing after: the keyframes after t go, and
  // one at t holds the pose commanded for t (a new command takes over from there).
  void holdFrom(double t) {
    const BasePose at = pose(t);
    while (!keys_.empty() && keys_.back().t > t) keys_.pop_back();
    if (keys_.empty() || keys_.back().t < t) keys_.push_back({t, at});
  }
  // The keyframes after time t, (time, pose).
  std::vector<std::pair<double, BasePose>> keyframesAfter(double t) const {
    std::vector<std::pair<double, BasePose>> out;
    for (const auto& k : keys_)
      if (k.t > t) out.emplace_back(k.t, k.pose);
    return out;
  }
  // Time of the last keyframe before t (-infinity when there is none).
  double lastKeyTimeBefore(double t) const {
    for (auto it = keys_.rbegin(); it != keys_.rend(); ++it)
      if (it->t < t) return it->t;
    return -std::numeric_limits<double>::infinity();
  }
  // Time of the last keyframe (-infinity when there is none).
  double lastTime() const { return keys_.empty() ? -std::numeric_limits<double>::infinity() : keys_.back().t; }
  size_t size() const { return keys_.size(); }

 private:
  struct Key {
    double t;
    BasePose pose;
  };
  BasePose rest_;
  std::vector<Key> keys_;
};

}  // namespace needle_sim

#pragma once
// What one step hands to the output thread: numbers only (no strings, no messages), copied
// under the simulation's lock in a few microseconds; the output thread builds and sends the
// per-step messages (status, wrenches, targets) from it. Names come from the shared
// ObservableNames, rebuilt when the scene or its targets change.
#include <ros/time.h>

#include <array>
#include <cmath>
#include <memory>
#include <string>
#include <vector>

#include "needle_sim/command/command_guard.hpp"
#include "needle_sim/sim/observables.hpp"
#include "needle_sim/sim/realtime_schedule.hpp"

namespace needle_sim {

// The online estimate's prediction of a target (NodeAssimilation): its position at the end of
// the motion known and the covariance of the parameters (and a measured offset) [m^2].
struct TargetPrediction {
  double t = 0;  // the estimate's last sample
  Vec3 position = Vec3::Zero();
  Mat3 covariance = Mat3::Zero();
  // What TargetState and the rviz ellipsoid show: the covariance plus the discretisation's,
  // bound^2 on the diagonal (none for a bound that is not positive and finite).
  Mat3 withBound(double bound) const {
    Mat3 c = covariance;
    if (std::isfinite(bound) && bound > 0) c.diagonal().array() += bound * bound;
    return c;
  }
};

struct StepFrame {
  ros::Time stamp;
  std::shared_ptr<const ObservableNames> names;
  std::string state;    // waiting | running | failed
  std::string failure;  // empty unless failed
  Observables obs;      // not filled after a failure: a failed state is never published
  double step_ms = 0, step_ms_max = 0, publish_ms = 0, rtf = 0, display_range = 0, lag = 0;
  RealtimeSchedule::Counts deadlines;
  std::array<uint64_t, kGuardRules> guard{};
  uint64_t rejected = 0, clamped = 0, unconverged = 0;
  double constraint_residual = 0;
  int primary_target = 0;
  bool send_target_point = false, send_target_state = false;  // subscribed
  std::vector<TargetPrediction> predictions;  // per target, with send_target_state; empty: none
};

}  // namespace needle_sim

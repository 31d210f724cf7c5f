// Validation of commanded base poses (the ROS node's input guard), without a roscore:
// non-finite and zero orientations and out-of-workspace positions are rejected, too-fast
// commands are clamped to the speed limit along their direction, orientation converts to
// (axis, roll) in BaseTrajectory's convention.
#include <gtest/gtest.h>

#include <cmath>

#include "needle_sim/ros/simulator_ros.hpp"

using namespace needle_sim;

namespace {
const Vec3 lo(0, 0, 0), hi(0.04, 0.02, 0.02);
const BasePose rest{Vec3(-0.035, 0.01, 0.01), Vec3::UnitX(), 0.0};
}  // namespace

TEST(CommandCheck, RejectsNonFiniteZeroAndOutOfWorkspace) {
  const Eigen::Quaterniond id = Eigen::Quaterniond::Identity();
  const double nan = std::nan("");
  EXPECT_EQ(checkCommand(Vec3(nan, 0, 0), id, rest, rest, 1e-3, 0.05, lo, hi, 0.2).verdict,
            CommandCheck::Verdict::Reject);
  EXPECT_EQ(checkCommand(rest.position, Eigen::Quaterniond(nan, 0, 0, 0), rest, rest, 1e-3, 0.05, lo, hi, 0.2).verdict,
            CommandCheck::Verdict::Reject);
  EXPECT_EQ(checkCommand(rest.position, Eigen::Quaterniond(0, 0, 0, 0), rest, rest, 1e-3, 0.05, lo, hi, 0.2).verdict,
            CommandCheck::Verdict::Reject);
  EXPECT_EQ(checkCommand(Vec3(1.0, 0.01, 0.01), id, rest, rest, 1e-3, 0.05, lo, hi, 0.2).verdict,
            CommandCheck::Verdict::Reject);
  EXPECT_EQ(checkCommand(Vec3(0.0, 0.01, std::numeric_limits<double>::infinity()), id, rest, rest, 1e-3, 0.05, lo, hi,
                         0.2)
                .verdict,
            CommandCheck::Verdict::Reject);
}

TEST(CommandCheck, ClampsSpeedAlongTheCommandedDirection) {
  const Eigen::Quaterniond id = Eigen::Quaterniond::Identity();
  // 1 mm in 1 ms = 1 m/s against 0.05 m/s: moved 0.05 mm towards the target.
  const auto c = checkCommand(rest.position + Vec3(1e-3, 0, 0), id, rest, rest, 1e-3, 0.05, lo, hi, 0.2);
  EXPECT_EQ(c.verdict, CommandCheck::Verdict::Clamp);
  EXPECT_NEAR((c.pose.position - rest.position).norm(), 5e-5, 1e-15);
  EXPECT_NEAR(c.pose.position.x() - rest.position.x(), 5e-5, 1e-15);
  // The same step over 0.1 s is slow enough.
  EXPECT_EQ(checkCommand(rest.position + Vec3(1e-3, 0, 0), id, rest, rest, 0.1, 0.05, lo, hi, 0.2).verdict,
            CommandCheck::Verdict::Accept);
}

TEST(CommandCheck, OrientationToAxisAndRoll) {
  // x axis turned 30 degrees about z, then rolled 0.4 rad about the new axis.
  const Eigen::Quaterniond q = Eigen::Quaterniond(Eigen::AngleAxisd(M_PI / 6, Vec3::UnitZ())) *
                               Eigen::Quaterniond(Eigen::AngleAxisd(0.4, Vec3::UnitX()));
  const auto c = checkCommand(rest.position, q, rest, rest, 1e-3, 0.05, lo, hi, 0.2);
  ASSERT_EQ(c.verdict, CommandCheck::Verdict::Accept);
  EXPECT_NEAR((c.pose.direction - Vec3(std::cos(M_PI / 6), std::sin(M_PI / 6), 0)).norm(), 0, 1e-12);
  EXPECT_NEAR(c.pose.roll, 0.4, 1e-12);
  // The rest orientation (identity: x is the rest axis) is roll 0, axis unchanged.
  const auto r = checkCommand(rest.position, Eigen::Quaterniond::Identity(), rest, rest, 1e-3, 0.05, lo, hi, 0.2);
  EXPECT_NEAR((r.pose.direction - Vec3::UnitX()).norm(), 0, 1e-15);
  EXPECT_NEAR(r.pose.roll, 0, 1e-15);
}

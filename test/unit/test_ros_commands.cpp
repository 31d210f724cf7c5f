// Validation of commanded base poses (the ROS node's input guard), without a roscore:
// non-finite and zero orientations and out-of-workspace positions are rejected, too-fast
// commands are clamped to the speed limit along their direction, orientation converts to
// (axis, roll) in BaseTrajectory's convention.
#include <gtest/gtest.h>

#include <cmath>

#include "needle_sim/ros/simulator_ros.hpp"
#include "needle_sim/scene/scene_loader.hpp"

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

// The frames the node publishes for the needle (<needle>_tip, the path's poses) are in the
// command poses' convention for any rest direction and roll: at rest each node's frame is
// the scene's base orientation, and after the base is moved to a commanded pose the tip's
// frame reads back, through the command check, as that pose's axis and roll.
TEST(NodeFrame, FollowsTheCommandConvention) {
  const Vec3 dir(0.48, -0.6, -0.64);
  const Scene sc = parseScene(R"(
name: frame_test
time: {dt: 0.001, duration: 0.01}
solver: {mode: dynamic}
needles:
  - {name: n, length: 0.1, radius: 0.001, young: 2.0e11, poisson: 0.3, density: 7900.0, elements: 4,
     base: {position: [0, 0, 0], direction: [0.48, -0.6, -0.64], roll: 0.3}}
)", std::string(NEEDLE_SIM_SOURCE_DIR) + "/config/scenes/frame_test.yaml");
  Simulation sim(sc);
  NeedleBody& nd = sim.needle(0);
  const Eigen::Quaterniond rest = Eigen::Quaterniond::FromTwoVectors(Vec3::UnitX(), dir) * Eigen::AngleAxisd(0.3, Vec3::UnitX());
  for (int k = 0; k < nd.beam().numNodes(); ++k) EXPECT_LT(nodeFrame(nd, k).angularDistance(rest), 1e-12) << k;
  const BasePose at_rest = nd.trajectory().rest();
  const auto c0 = checkCommand(at_rest.position, nodeFrame(nd, 4), at_rest, at_rest, 1.0, 1.0, Vec3::Constant(-1),
                               Vec3::Constant(1), 0.0);
  ASSERT_EQ(c0.verdict, CommandCheck::Verdict::Accept) << c0.reason;
  EXPECT_LT((c0.pose.direction - dir).norm(), 1e-12);
  EXPECT_NEAR(c0.pose.roll, 0.3, 1e-12);

  const BasePose moved{Vec3(0.01, 0.0, 0.0), Vec3(0.0, 1.0, 0.2).normalized(), 0.7};
  nd.trajectory().add(1.0, moved);
  nd.placeAt(1.0);
  const auto c1 = checkCommand(moved.position, nodeFrame(nd, 4), at_rest, at_rest, 1.0, 1.0, Vec3::Constant(-1),
                               Vec3::Constant(1), 0.0);
  ASSERT_EQ(c1.verdict, CommandCheck::Verdict::Accept) << c1.reason;
  EXPECT_LT((c1.pose.direction - moved.direction).norm(), 1e-12);
  EXPECT_NEAR(c1.pose.roll, 0.7, 1e-12);
}

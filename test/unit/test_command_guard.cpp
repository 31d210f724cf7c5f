// The command guard (the node's last check before the needle moves), without ROS: each rule
// rejects or slows down what breaks it and counts it; the base trajectory it builds never
// moves faster than the limits (sampled finely), after a pause, a future stamp, a non-unit
// quaternion or a large turn too; plans are checked whole; the pose convention reads back.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>

#include "needle_sim/command/command_guard.hpp"
#include "needle_sim/command/pose_convention.hpp"
#include "needle_sim/core/error.hpp"
#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/sim/observables.hpp"
#include "needle_sim/sim/prediction.hpp"
#include "needle_sim/sim/realtime_schedule.hpp"
#include "needle_sim/sim/simulation.hpp"
#include "needle_sim/sim/tip_speed.hpp"

using namespace needle_sim;

namespace {

const BasePose kRest{Vec3(-0.035, 0.01, 0.01), Vec3::UnitX(), 0.0};
const double kDt = 1e-3;

CommandLimits limits() {
  CommandLimits l;
  l.max_speed = 0.05;
  l.max_angular_speed = 1.0;
  l.max_angular_speed_inserted = 0.1;
  l.max_future = 0.01;
  l.command_timeout = 0.5;
  l.command_latency = 0.005;
  l.workspace_min = Vec3(0, 0, 0);
  l.workspace_max = Vec3(0.04, 0.02, 0.02);
  return l;
}

CommandGuard guard() { return CommandGuard(limits(), {{kRest, 0.032}}); }

PoseCommand at(const Vec3& p, double stamp, const Eigen::Quaterniond& q = Eigen::Quaterniond::Identity()) {
  PoseCommand c;
  c.position = p;
  c.orientation = q;
  c.stamp = stamp;
  return c;
}

// Largest linear and angular speed of the trajectory over [t0, t1], by finite differences.
struct Rates {
  double linear = 0, angular = 0, axis = 0;
};
Rates sampledRates(const BaseTrajectory& traj, double t0, double t1) {
  Rates r;
  const double h = 1e-5;
  BasePose prev = traj.pose(t0);
  for (double t = t0 + h; t <= t1; t += h) {
    const BasePose p = traj.pose(t);
    r.linear = std::max(r.linear, (p.position - prev.position).norm() / h);
    r.angular = std::max(r.angular, traj.orientation(p).angularDistance(traj.orientation(prev)) / h);
    r.axis = std::max(r.axis, std::acos(std::clamp(p.direction.dot(prev.direction), -1.0, 1.0)) / h);
    prev = p;
  }
  return r;
}

}  // namespace

TEST(CommandGuard, RejectsNonFiniteNonUnitAndOutOfWorkspaceAndCountsEachRule) {
  CommandGuard g = guard();
  const double nan = std::nan(""), inf = std::numeric_limits<double>::infinity();
  EXPECT_FALSE(g.admit(0, at(Vec3(nan, 0, 0), 0), 0).accepted);
  EXPECT_FALSE(g.admit(0, at(Vec3(0, 0.01, inf), 0), 0).accepted);
  EXPECT_FALSE(g.admit(0, at(kRest.position, 0, Eigen::Quaterniond(nan, 0, 0, 0)), 0).accepted);
  EXPECT_EQ(g.count(GuardRule::NonFinite), 3u);
  // Zero and (2, 2, 2, 2): rejected, not normalised into a turn.
  EXPECT_FALSE(g.admit(0, at(kRest.position, 0, Eigen::Quaterniond(0, 0, 0, 0)), 0).accepted);
  const Admission big = g.admit(0, at(kRest.position, 0, Eigen::Quaterniond(2, 2, 2, 2)), 0);
  EXPECT_FALSE(big.accepted);
  EXPECT_EQ(big.rule, GuardRule::Quaternion);
  EXPECT_NE(big.reason.find("norm 4"), std::string::npos) << big.reason;
  EXPECT_EQ(g.count(GuardRule::Quaternion), 2u);
  // Within the tolerance (a float-rounded quaternion): accepted.
  EXPECT_TRUE(g.admit(0, at(kRest.position, 0, Eigen::Quaterniond(1.0001, 0, 0, 0)), 0).accepted);
  EXPECT_FALSE(g.admit(0, at(Vec3(1.0, 0.01, 0.01), 0.001), 0.001).accepted);
  EXPECT_EQ(g.count(GuardRule::Workspace), 1u);
  EXPECT_EQ(g.rejected(), 6u);
  EXPECT_EQ(g.limited(), 0u);
}

TEST(CommandGuard, StampsFromTheFutureStaleOrOutOfOrderAreRejected) {
  CommandGuard g = guard();
  // 10 s ahead: rejected (clock skew), and the later, normal commands are taken on time.
  const Admission future = g.admit(0, at(kRest.position + Vec3(1e-3, 0, 0), 11.0), 1.0);
  EXPECT_FALSE(future.accepted);
  EXPECT_EQ(future.rule, GuardRule::Future);
  const Admission a = g.admit(0, at(kRest.position, 1.0), 1.0);
  ASSERT_TRUE(a.accepted) << a.reason;
  EXPECT_DOUBLE_EQ(a.at, 1.0 + 0.005);
  // Within ~max_future: accepted.
  EXPECT_TRUE(g.admit(0, at(kRest.position, 1.008), 1.0).accepted);
  // Older than the last accepted one: out of order; the same stamp again is fine.
  const Admission back = g.admit(0, at(kRest.position, 1.004), 1.009);
  EXPECT_FALSE(back.accepted);
  EXPECT_EQ(back.rule, GuardRule::OutOfOrder);
  EXPECT_TRUE(g.admit(0, at(kRest.position, 1.008), 1.009).accepted);
  // Older than ~command_timeout: stale.
  EXPECT_EQ(g.admit(0, at(kRest.position, 1.2), 1.8).rule, GuardRule::Stale);
  // Unstamped: taken as received now.
  const Admission u = g.admit(0, at(kRest.position, std::nan("")), 2.0);
  ASSERT_TRUE(u.accepted);
  EXPECT_DOUBLE_EQ(u.at, 2.005);
  EXPECT_EQ(g.count(GuardRule::Future), 1u);
  EXPECT_EQ(g.count(GuardRule::OutOfOrder), 1u);
  EXPECT_EQ(g.count(GuardRule::Stale), 1u);
  // restart(): the stamp order starts again, the counters stay.
  g.restart();
  EXPECT_TRUE(g.admit(0, at(kRest.position, 0.0), 0.0).accepted);
  EXPECT_EQ(g.rejected(), 3u);
}

TEST(CommandGuard, AJumpIsApproachedAtTheSpeedLimitAlsoAfterAPause) {
  CommandGuard g = guard();
  BaseTrajectory traj(kRest);
  // A stream at the limit (0.05 m/s, 500 Hz) is followed exactly, on time.
  double now = 0;
  for (int k = 1; k <= 100; ++k) {
    const double stamp = 0.002 * k;
    now = stamp;
    const Admission a = g.admit(0, at(kRest.position + Vec3(0.05 * stamp, 0, 0), stamp), now);
    ASSERT_TRUE(a.accepted);
    const Following f = g.follow(0, traj, a, now, kDt, false);
    EXPECT_FALSE(f.limited) << k;
    EXPECT_NEAR(f.reached_at, stamp + 0.005, 1e-12);
  }
  EXPECT_EQ(g.limited(), 0u);
  // 2 s of silence, then a 20 mm jump: approached at the limit from where the base is
  // (0.4 s), not in one step.
  now = 2.2;
  const Vec3 held = traj.pose(now).position;
  const Admission jump = g.admit(0, at(held + Vec3(0.02, 0, 0), now), now);
  ASSERT_TRUE(jump.accepted);
  const Following f = g.follow(0, traj, jump, now, kDt, false);
  EXPECT_TRUE(f.limited);
  EXPECT_EQ(f.rule, GuardRule::LinearSpeed);
  EXPECT_NEAR(f.reached_at, now + 0.4, 1e-9);
  EXPECT_EQ(g.count(GuardRule::LinearSpeed), 1u);
  const Rates r = sampledRates(traj, 0.0, 3.0);
  EXPECT_LE(r.linear, 0.05 * (1 + 1e-6));
  EXPECT_NEAR((traj.pose(3.0).position - held).norm(), 0.02, 1e-12);
  // A later command supersedes the one not reached yet: it takes over from where the base
  // is at its own time, still at the limit (no jump back).
  const double t2 = now + 0.1;
  const Admission back = g.admit(0, at(held, t2), t2);
  g.follow(0, traj, back, t2, kDt, false);
  EXPECT_LE(sampledRates(traj, 0.0, 3.0).linear, 0.05 * (1 + 1e-6));
  EXPECT_NEAR((traj.pose(4.0).position - held).norm(), 0.0, 1e-12);
}

// A stream well within the limits (1 cm/s, 100 Hz) that reaches the node late (15 ms, every
// other sample skipped, as a lagging node sampling tf sees it) is not a clamped command: the
// base catches up within the limit, and nothing is counted. A jump that arrives late is.
TEST(CommandGuard, ALateStreamWithinTheLimitsIsNotCountedAsClamped) {
  CommandGuard g = guard();
  BaseTrajectory traj(kRest);
  double now = 0;
  for (int k = 1; k <= 100; ++k) {
    const double stamp = 0.01 * k;
    if (k % 2 == 1) continue;  // skipped: the node looked up tf only every 20 ms
    now = stamp + 0.015;
    const Admission a = g.admit(0, at(kRest.position + Vec3(0.01 * stamp, 0, 0), stamp), now);
    ASSERT_TRUE(a.accepted);
    const Following f = g.follow(0, traj, a, now, kDt, false);
    EXPECT_FALSE(f.limited) << k;
  }
  EXPECT_EQ(g.limited(), 0u);
  EXPECT_LE(sampledRates(traj, 0.0, now + 0.1).linear, 0.05 * (1 + 1e-6));
  EXPECT_NEAR(traj.pose(now + 0.1).position.x() - kRest.position.x(), 0.01, 1e-12);
  // The node stalls 40 ms: eight 200 Hz samples of the same 1 cm/s motion come in one step.
  // Each supersedes the one before, unreached; the batch had the whole stall for its motion.
  const Vec3 p1 = kRest.position + Vec3(0.01, 0, 0);
  const double s1 = 1.0;
  now = s1 + 0.045;
  for (int k = 1; k <= 8; ++k) {
    const double stamp = s1 + 0.005 * k;
    const Admission a = g.admit(0, at(p1 + Vec3(0.01 * (stamp - s1), 0, 0), stamp), now);
    ASSERT_TRUE(a.accepted);
    EXPECT_FALSE(g.follow(0, traj, a, now, kDt, false).limited) << k;
  }
  EXPECT_EQ(g.limited(), 0u);
  EXPECT_LE(sampledRates(traj, 0.0, now + 0.1).linear, 0.05 * (1 + 1e-6));
  // 20 mm asked right after the batch, arriving 15 ms late: too fast for any stream.
  const double stamp = s1 + 0.045;
  now = stamp + 0.015;
  const Admission jump = g.admit(0, at(p1 + Vec3(0.02, 0, 0), stamp), now);
  ASSERT_TRUE(jump.accepted);
  EXPECT_TRUE(g.follow(0, traj, jump, now, kDt, false).limited);
  EXPECT_EQ(g.count(GuardRule::LinearSpeed), 1u);
  EXPECT_LE(sampledRates(traj, 0.0, now + 1.0).linear, 0.05 * (1 + 1e-6));
}

TEST(CommandGuard, TurnsAreLimitedAndMoreSoInsideTheTissue) {
  CommandGuard g = guard();
  BaseTrajectory traj(kRest);
  // 120 degrees about (1,1,1) at once: 2.09 s at 1 rad/s.
  const Eigen::Quaterniond turn(Eigen::AngleAxisd(2 * M_PI / 3, Vec3(1, 1, 1).normalized()));
  const Admission a = g.admit(0, at(kRest.position, 0.0, turn), 0.0);
  ASSERT_TRUE(a.accepted);
  const Following f = g.follow(0, traj, a, 0.0, kDt, false);
  EXPECT_TRUE(f.limited);
  EXPECT_EQ(f.rule, GuardRule::AngularSpeed);
  EXPECT_GT(f.reached_at, 2 * M_PI / 3 - 1e-6);
  Rates r = sampledRates(traj, 0.0, f.reached_at + 0.1);
  EXPECT_LE(r.angular, 1.0 * 1.002);
  EXPECT_LT(traj.orientation(traj.pose(f.reached_at)).angularDistance(traj.orientation(a.pose)), 1e-9);

  // Inside the tissue a 90 degree turn of the axis takes 15.7 s at 0.1 rad/s.
  CommandGuard g2 = guard();
  BaseTrajectory t2(kRest);
  const Eigen::Quaterniond tilt(Eigen::AngleAxisd(M_PI / 2, Vec3::UnitZ()));
  const Admission b = g2.admit(0, at(kRest.position, 0.0, tilt), 0.0);
  const Following fb = g2.follow(0, t2, b, 0.0, kDt, true);
  EXPECT_EQ(fb.rule, GuardRule::AngularInserted);
  EXPECT_NEAR(fb.reached_at, M_PI / 2 / 0.1, 0.01);
  r = sampledRates(t2, 0.0, fb.reached_at);
  EXPECT_LE(r.axis, 0.1 * 1.002);
  // A roll about the axis inside the tissue is held to the general limit only (steering
  // spins the needle).
  CommandGuard g3 = guard();
  BaseTrajectory t3(kRest);
  const Admission c = g3.admit(0, at(kRest.position, 0.0, Eigen::Quaterniond(Eigen::AngleAxisd(0.5, Vec3::UnitX()))), 0.0);
  const Following fc = g3.follow(0, t3, c, 0.0, kDt, true);
  EXPECT_NEAR(fc.reached_at, 0.5, 1e-3);
}

TEST(CommandGuard, RollIsUnwrappedNoFullTurnBetweenNearlyEqualPoses) {
  CommandGuard g = guard();
  // A roll stream crossing +-pi: each command's roll stays within pi of the previous one.
  double prev = 0;
  for (int k = 0; k <= 40; ++k) {
    const double roll = 0.1 * k;  // up to 4 rad
    Eigen::Quaterniond q(Eigen::AngleAxisd(roll, Vec3::UnitX()));
    if (k % 2) q.coeffs() *= -1;  // the same rotation
    const Admission a = g.admit(0, at(kRest.position, 0.01 * k, q), 0.01 * k);
    ASSERT_TRUE(a.accepted);
    EXPECT_NEAR(a.pose.roll, roll, 1e-9) << k;
    EXPECT_LT(std::abs(a.pose.roll - prev), 0.1 + 1e-9);
    prev = a.pose.roll;
  }
}

TEST(CommandGuard, PlansAreCheckedWhole) {
  CommandGuard g = guard();
  PlanPoses out;
  auto wp = [](double t, double x, const Eigen::Quaterniond& q = Eigen::Quaterniond::Identity()) {
    return PlanWaypoint{t, Vec3(x, 0.01, 0.01), q};
  };
  // 1 cm in 1 s: fine.
  EXPECT_EQ(g.checkPlan(0, {wp(0.5, -0.030), wp(1.0, -0.025)}, kRest, kDt, false, out), "");
  ASSERT_EQ(out.size(), 2u);
  EXPECT_NEAR(out[1].second.position.x(), -0.025, 1e-15);
  // 1 cm in 0.1 s: refused, not changed.
  std::string why = g.checkPlan(0, {wp(0.1, -0.025)}, kRest, kDt, false, out);
  EXPECT_NE(why.find("waypoint 0: linear_speed"), std::string::npos) << why;
  EXPECT_TRUE(out.empty());
  why = g.checkPlan(0, {wp(0.5, -0.030), wp(0.4, -0.025)}, kRest, kDt, false, out);
  EXPECT_NE(why.find("waypoint 1: time_from_start"), std::string::npos) << why;
  why = g.checkPlan(0, {wp(1.0, -0.035, Eigen::Quaterniond(2, 2, 2, 2))}, kRest, kDt, false, out);
  EXPECT_NE(why.find("quaternion_norm"), std::string::npos) << why;
  why = g.checkPlan(0, {wp(0.1, -0.035, Eigen::Quaterniond(Eigen::AngleAxisd(1.0, Vec3::UnitZ())))}, kRest, kDt, false, out);
  EXPECT_NE(why.find("angular_speed"), std::string::npos) << why;
  // A turn of the axis at 0.5 rad/s: fine outside the tissue, refused with the tip inside
  // (the rigid tip of a base at x = 0 lies in the box).
  const Eigen::Quaterniond small(Eigen::AngleAxisd(0.5, Vec3::UnitZ()));
  EXPECT_EQ(g.checkPlan(0, {wp(1.0, -0.035, small)}, kRest, kDt, false, out), "");
  const BasePose in{Vec3(0.0, 0.01, 0.01), Vec3::UnitX(), 0.0};
  why = g.checkPlan(0, {PlanWaypoint{1.0, in.position, small}}, in, kDt, false, out);
  EXPECT_NE(why.find("angular_speed_inserted"), std::string::npos) << why;
  EXPECT_EQ(g.count(GuardRule::Plan), 5u);
  EXPECT_EQ(g.checkPlan(0, {}, kRest, kDt, false, out), "no waypoints");
}

// Duty-cycled spinning in a plan (a bevel tip's curvature between its maximum and ~0):
// the segment becomes whole turns and holds, the turns no faster than the angular limit, the
// later waypoints' rolls advanced by the turns; bad spins are refused whole, by waypoint.
TEST(CommandGuard, APlanWithDutyCycledSpinningBecomesWholeTurnsWithinTheLimit) {
  CommandGuard g = guard();  // max_angular_speed 1 rad/s
  PlanPoses out;
  auto wp = [](double t, double x, double rate = 0, double duty = 0) {
    PlanWaypoint w{t, Vec3(x, 0.01, 0.01), Eigen::Quaterniond::Identity()};
    w.spin_rate = rate;
    w.spin_duty = duty;
    return w;
  };
  // Half of 4 pi s spinning at 1 rad/s: one whole turn in 2 pi s, then a hold of 2 pi s.
  const double t0 = 0.5, T = 4 * M_PI;
  ASSERT_EQ(g.checkPlan(0, {wp(t0, -0.030, 1.0, 0.5), wp(t0 + T, -0.025)}, kRest, kDt, false, out), "");
  ASSERT_EQ(out.size(), 3u);
  EXPECT_NEAR(out[1].first, t0 + T / 2, 1e-12);
  EXPECT_NEAR(out[1].second.position.x(), -0.0275, 1e-12);
  EXPECT_NEAR(out[1].second.roll - out[0].second.roll, 2 * M_PI, 1e-12);
  EXPECT_NEAR(out[2].second.roll - out[0].second.roll, 2 * M_PI, 1e-12);  // the base does not unwind
  EXPECT_NEAR(out[2].second.position.x(), -0.025, 1e-15);
  BaseTrajectory traj(kRest);
  for (const auto& [t, p] : out) traj.add(t, p);
  const Rates r = sampledRates(traj, t0, t0 + T);
  EXPECT_LE(r.angular, 1.0 + 1e-3);
  EXPECT_GT(r.angular, 0.99);  // it does turn, at the rate asked
  EXPECT_EQ(g.count(GuardRule::Plan), 0u);

  auto refused = [&](const std::vector<PlanWaypoint>& w, const std::string& what) {
    const std::string why = g.checkPlan(0, w, kRest, kDt, false, out);
    EXPECT_NE(why.find(what), std::string::npos) << why;
    EXPECT_TRUE(out.empty());
  };
  refused({wp(t0, -0.030, 1.0, 1.5), wp(t0 + T, -0.025)}, "waypoint 0: spin_duty 1.5");
  refused({wp(t0, -0.030, 1.0, -0.1), wp(t0 + T, -0.025)}, "spin_duty");
  refused({wp(t0, -0.030, 0.0, 0.5), wp(t0 + T, -0.025)}, "spin_rate > 0");
  refused({wp(t0, -0.030, 2.0, 0.5), wp(t0 + T, -0.025)}, "spin_rate 2 rad/s, faster than max_angular_speed");
  refused({wp(t0, -0.030), wp(t0 + T, -0.025, 1.0, 0.5)}, "waypoint 1: spin on the last waypoint");
  refused({wp(t0, -0.030, std::nan(""), 0.5), wp(t0 + T, -0.025)}, "finite");
  // 0.6 of a turn asked for: rounded to one whole turn, in less time than the rate allows;
  // the refusal names the waypoint whose segment spins.
  refused({wp(t0, -0.030, 1.0, 0.5), wp(t0 + 2.4 * M_PI, -0.025)}, "waypoint 0: angular_speed: the spin's whole turns run at 1.667 rad/s");
  refused({wp(t0, -0.030), wp(t0 + 1, -0.029, 1.0, 1.0), wp(t0 + 1 + 1.4 * M_PI, -0.028)},
          "waypoint 1: angular_speed: the spin's whole turns run at 1.429 rad/s");
  EXPECT_EQ(g.count(GuardRule::Plan), 8u);
  // Spinning all the time (duty 1), two turns: turn ends only, no hold, times increasing.
  ASSERT_EQ(g.checkPlan(0, {wp(t0, -0.030, 1.0, 1.0), wp(t0 + T, -0.025)}, kRest, kDt, false, out), "");
  ASSERT_EQ(out.size(), 3u);
  EXPECT_NEAR(out[1].first, t0 + T / 2, 1e-12);
  EXPECT_NEAR(out[1].second.roll - out[0].second.roll, 2 * M_PI, 1e-12);
  EXPECT_NEAR(out[2].second.roll - out[0].second.roll, 4 * M_PI, 1e-12);
  for (size_t i = 1; i < out.size(); ++i) EXPECT_GT(out[i].first, out[i - 1].first);
}

TEST(CommandGuard, LimitsAreValidated) {
  CommandLimits l = limits();
  l.max_speed = 0;
  EXPECT_THROW(l.validate(), InputError);
  l = limits();
  l.max_angular_speed_inserted = 2.0;  // above max_angular_speed
  EXPECT_THROW(l.validate(), InputError);
  l = limits();
  l.quaternion_tolerance = std::nan("");
  EXPECT_THROW(l.validate(), InputError);
  CommandGuard g = guard();
  l = limits();
  l.max_speed = -1;
  EXPECT_THROW(g.setLimits(l), InputError);
  EXPECT_DOUBLE_EQ(g.limits().max_speed, 0.05);  // unchanged
  l.max_speed = 0.01;
  g.setLimits(l);
  BaseTrajectory traj(kRest);
  const Admission a = g.admit(0, at(kRest.position + Vec3(0.01, 0, 0), 0.0), 0.0);
  EXPECT_NEAR(g.follow(0, traj, a, 0.0, kDt, false).reached_at, 1.0, 1e-9);  // 1 cm at 1 cm/s
}

TEST(PoseConvention, OrientationToAxisAndRoll) {
  // x axis turned 30 degrees about z, then rolled 0.4 rad about the new axis.
  const Eigen::Quaterniond q = Eigen::Quaterniond(Eigen::AngleAxisd(M_PI / 6, Vec3::UnitZ())) *
                               Eigen::Quaterniond(Eigen::AngleAxisd(0.4, Vec3::UnitX()));
  const BasePose p = basePoseFrom(kRest.position, q, kRest, 0.0);
  EXPECT_NEAR((p.direction - Vec3(std::cos(M_PI / 6), std::sin(M_PI / 6), 0)).norm(), 0, 1e-12);
  EXPECT_NEAR(p.roll, 0.4, 1e-12);
  EXPECT_LT(orientationOf(p, kRest).angularDistance(q), 1e-12);
  // The rest orientation (identity: x is the rest axis) is roll 0, axis unchanged.
  const BasePose r = basePoseFrom(kRest.position, Eigen::Quaterniond::Identity(), kRest, 0.0);
  EXPECT_NEAR((r.direction - Vec3::UnitX()).norm(), 0, 1e-15);
  EXPECT_NEAR(r.roll, 0, 1e-15);
}

// The frames the node publishes for the needle (<needle>_tip, the path's poses) are in the
// command poses' convention for any rest direction and roll: at rest each node's frame is
// the scene's base orientation, and after the base is moved to a commanded pose the tip's
// frame reads back as that pose's axis and roll.
TEST(PoseConvention, NodeFramesFollowTheCommandConvention) {
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
  const BasePose p0 = basePoseFrom(at_rest.position, nodeFrame(nd, 4), at_rest, 0.0);
  EXPECT_LT((p0.direction - dir).norm(), 1e-12);
  EXPECT_NEAR(p0.roll, 0.3, 1e-12);

  const BasePose moved{Vec3(0.01, 0.0, 0.0), Vec3(0.0, 1.0, 0.2).normalized(), 0.7};
  nd.trajectory().add(1.0, moved);
  nd.placeAt(1.0);
  const BasePose p1 = basePoseFrom(moved.position, nodeFrame(nd, 4), at_rest, 0.0);
  EXPECT_LT((p1.direction - moved.direction).norm(), 1e-12);
  EXPECT_NEAR(p1.roll, 0.7, 1e-12);
  // The observables carry the same frames.
  const Observables o = observe(sim);
  EXPECT_LT(o.needles[0].tip_frame.angularDistance(nodeFrame(nd, 4)), 1e-15);
  EXPECT_LT(o.needles[0].base_frame.angularDistance(nodeFrame(nd, 0)), 1e-15);
}

// The holder's wrench: a static cantilever with a tip load passes the load to the holder.
// In the base frame (x along the needle) a lateral tip force y reads +y on the holder, and
// the moment about the base node is r x F.
TEST(Observables, HolderWrenchOfALoadedCantilever) {
  Scene sc = loadScene(std::string(NEEDLE_SIM_SOURCE_DIR) + "/config/scenes/needle_cantilever.yaml",
                       {"needle.base.direction=[0,0,1]", "needle.tip_force=[0.01,0,0]"});
  Simulation sim(sc);
  sim.step();
  const Observables o = observe(sim);
  ASSERT_EQ(o.needles.size(), 1u);
  const NeedleObservation& n = o.needles[0];
  // Tissue frame: the holder feels the tip force; the moment about the base is tip x F.
  EXPECT_LT((n.holder_force - Vec3(0.01, 0, 0)).norm(), 1e-9);
  EXPECT_LT((n.holder_moment - (n.tip - n.base).cross(Vec3(0.01, 0, 0))).norm(), 1e-9);
  // Base frame: the needle axis (tissue z) is its x.
  // (The static solve's residual leaves the wrench accurate to about 1e-9 N.)
  EXPECT_LT((n.holder_force_base - n.base_frame.conjugate() * Vec3(0.01, 0, 0)).norm(), 1e-9);
  EXPECT_NEAR(n.holder_force_base.x(), 0.0, 1e-9);  // no axial load
  EXPECT_NEAR(n.holder_force_base.norm(), 0.01, 1e-9);
}

TEST(RealtimeSchedule, TellsLateStepsFromSkippedTicks) {
  RealtimeSchedule s(0.001);
  s.start(0.0);
  // Ticks every millisecond; steps 1..10 on time (done within their period).
  for (int k = 1; k <= 10; ++k) {
    EXPECT_EQ(s.tick(0.001 * k), 1);
    EXPECT_TRUE(s.takeStep());
    s.stepDone(k, 0.001 * k + 0.0005);
  }
  auto c = s.counts(0.0105);
  EXPECT_EQ(c.late, 0u);
  EXPECT_EQ(c.skipped, 0u);
  // Step 11 takes 3.5 ms: it is late; the tick at 13 ms finds step 12 not yet started (a
  // skipped tick); 12 and 13 then run back to back, late too.
  EXPECT_EQ(s.tick(0.011), 1);
  EXPECT_TRUE(s.takeStep());
  EXPECT_EQ(s.tick(0.012), 1);
  EXPECT_EQ(s.tick(0.013), 1);  // step 12 still pending: a skipped tick
  s.stepDone(11, 0.0145);       // due by 0.012: late
  EXPECT_TRUE(s.takeStep());
  s.stepDone(12, 0.0147);  // due by 0.013: late
  EXPECT_TRUE(s.takeStep());
  s.stepDone(13, 0.0149);  // due by 0.014: late
  EXPECT_FALSE(s.takeStep());
  c = s.counts(0.015);
  EXPECT_EQ(c.late, 3u);
  EXPECT_EQ(c.skipped, 1u);
  EXPECT_EQ(c.longest_late_run, 3);
  EXPECT_NEAR(c.late_fraction, 3.0 / 13, 1e-9);    // of the 13 steps done since the start
  EXPECT_NEAR(c.skipped_fraction, 1.0 / 15, 1e-9);  // of the 15 ticks due
  // A second later, the rates have forgotten them; the lifetime counts have not.
  c = s.counts(1.1);
  EXPECT_EQ(c.late_per_s, 0.0);
  EXPECT_EQ(c.late, 3u);
  // The clock going back asks for a restart; start() keeps the lifetime counts.
  EXPECT_EQ(s.tick(0.005), -1);
  s.start(0.0);
  EXPECT_EQ(s.counts(0.0).late, 3u);
}

// Found by an outside-in trial: waypoints closer together than a step were given a step
// each in the check (10x the speed limit got through); now each segment is checked over its
// own duration.
TEST(CommandGuard, APlanOfDenseWaypointsIsCheckedAtItsOwnPace) {
  CommandGuard g = guard();
  PlanPoses out;
  std::vector<PlanWaypoint> dense;
  for (int k = 1; k <= 200; ++k)
    dense.push_back({1e-4 * k + 1e-3, Vec3(-0.035, 0.01 - 5e-5 * k, 0.01), Eigen::Quaterniond::Identity()});
  const std::string why = g.checkPlan(0, dense, kRest, kDt, false, out);
  EXPECT_NE(why.find("linear_speed: 0.5 m/s"), std::string::npos) << why;
  // The same path at 0.04 m/s is fine.
  for (int k = 0; k < 200; ++k) dense[k].time = 1e-3 + 1.25e-3 * (k + 1);
  EXPECT_EQ(g.checkPlan(0, dense, kRest, kDt, false, out), "");
  // A second waypoint inside the plan's first step would be merged into the first: refused.
  EXPECT_NE(g.checkPlan(0, {{2e-4, kRest.position, Eigen::Quaterniond::Identity()},
                            {6e-4, kRest.position, Eigen::Quaterniond::Identity()}},
                        kRest, kDt, false, out)
                .find("first step"),
            std::string::npos);
}

// Found by an outside-in trial: a command that turns the needle while it enters the tissue
// was limited by the general angular limit only (the needle was outside when it started).
TEST(CommandGuard, TheInTissueTurnLimitAppliesWhereTheMotionEntersTheTissue) {
  CommandGuard g = guard();
  BaseTrajectory traj(kRest);
  // From outside (tip at -3 mm) to 10 mm in, turning 15 degrees about z.
  const Eigen::Quaterniond yaw(Eigen::AngleAxisd(M_PI / 12, Vec3::UnitZ()));
  const Admission a = g.admit(0, at(kRest.position + Vec3(0.013, 0, 0), 0.0, yaw), 0.0);
  ASSERT_TRUE(a.accepted);
  const Following f = g.follow(0, traj, a, 0.0, kDt, false);
  EXPECT_EQ(f.rule, GuardRule::AngularInserted);
  const Rates r = sampledRates(traj, 0.0, f.reached_at);
  EXPECT_LE(r.axis, 0.1 * 1.002);
  // The same motion as a plan at the general limit: refused (the tip enters the tissue).
  PlanPoses out;
  const std::string why =
      g.checkPlan(0, {{(M_PI / 12) / 0.9, kRest.position + Vec3(0.013, 0, 0), yaw}}, kRest, kDt, false, out);
  EXPECT_NE(why.find("angular_speed_inserted"), std::string::npos) << why;
}

// Found by an outside-in trial: limits lowered at run time applied to new commands only.
TEST(CommandGuard, LoweredLimitsSlowDownTheMotionUnderWay) {
  CommandGuard g = guard();
  BaseTrajectory traj(kRest);
  PlanPoses out;
  ASSERT_EQ(g.checkPlan(0, {{1.0, kRest.position + Vec3(-0.04, 0, 0), Eigen::Quaterniond::Identity()}}, kRest, kDt,
                        false, out),
            "");
  traj.replaceFrom(0.0, kDt, out);  // 40 mm in 1 s: at 0.04 m/s
  CommandLimits l = g.limits();
  const long v = g.limitsVersion();
  l.max_speed = 0.01;
  g.setLimits(l);
  EXPECT_EQ(g.limitsVersion(), v + 1);
  EXPECT_TRUE(g.enforce(0, traj, 0.3, false));
  const Rates r = sampledRates(traj, 0.3, 5.0);
  EXPECT_LE(r.linear, 0.01 * (1 + 1e-6));
  EXPECT_NEAR(traj.lastTime(), 0.3 + 0.028 / 0.01, 1e-9);  // the 28 mm left, at 10 mm/s
  EXPECT_LT((traj.pose(10.0).position - (kRest.position + Vec3(-0.04, 0, 0))).norm(), 1e-12);  // still gets there
  EXPECT_FALSE(g.enforce(0, traj, 0.3, false));  // within the limits now: unchanged
}

// Issue #39: dynamic_reconfigure clamped max_speed 1e9 to 1 m/s and applied it. The core
// refuses a limit above its ceiling (start-up parameters ~<limit>_ceiling) and any value that
// is not positive and finite, whole: the limits stay as they were.
TEST(CommandGuard, LimitsAboveTheirCeilingOrNotFiniteAreRefusedWhole) {
  CommandGuard g = guard();  // default ceilings: max_speed 0.1 m/s
  const double inf = std::numeric_limits<double>::infinity();
  for (double v : {1e9, inf, 0.1000001, -1.0, 0.0, std::nan("")}) {
    CommandLimits l = limits();
    l.max_speed = v;
    l.max_future = 0.02;  // a valid change in the same set: refused with it
    try {
      g.setLimits(l);
      ADD_FAILURE() << "max_speed " << v << " was taken";
    } catch (const InputError& e) {
      EXPECT_EQ(e.key(), "max_speed") << v;  // the core names limits bare; the node adds "~"
      if (std::isfinite(v) && v > 0.1) {
        EXPECT_NE(std::string(e.what()).find("max_speed_ceiling = 0.1 m/s"), std::string::npos) << e.what();
      }
    }
    EXPECT_DOUBLE_EQ(g.limits().max_speed, 0.05) << v;
    EXPECT_DOUBLE_EQ(g.limits().max_future, 0.01) << v;
  }
  // At the ceiling: taken.
  CommandLimits l = limits();
  l.max_speed = 0.1;
  g.setLimits(l);
  EXPECT_DOUBLE_EQ(g.limits().max_speed, 0.1);
  // Each widening limit has its ceiling, named in the refusal.
  LimitCeilings c;
  c.max_angular_speed_inserted = 0.2;
  c.workspace_margin = 0.3;
  CommandGuard h(limits(), {{kRest, 0.032}}, c, "~");  // named as the node's parameters
  l = limits();
  l.max_angular_speed_inserted = 0.5;
  try {
    h.setLimits(l);
    ADD_FAILURE() << "above the ceiling, taken";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("~max_angular_speed_inserted_ceiling = 0.2 rad/s"), std::string::npos)
        << e.what();
  }
  l = limits();
  l.workspace_margin = 0.5;
  EXPECT_THROW(h.setLimits(l), InputError);
  EXPECT_DOUBLE_EQ(h.limits().workspace_margin, 0.2);
  // Start-up limits above a ceiling, or a ceiling that is not positive and finite: refused.
  c = LimitCeilings();
  c.max_speed = 0.01;
  EXPECT_THROW(CommandGuard(limits(), {{kRest, 0.032}}, c), InputError);
  c.max_speed = inf;
  EXPECT_THROW(CommandGuard(limits(), {{kRest, 0.032}}, c), InputError);
}

// Issue #39: two processes commanding one needle got no arbitration. One source at a time:
// the first whose command is taken owns the needle until it has been silent for
// owner_timeout (0.5 s); an explicit holder keeps it until it releases it; a plan keeps it
// until its end.
TEST(CommandGuard, OneSourceCommandsANeedleAtATime) {
  CommandGuard g = guard();
  auto from = [](const std::string& who, double stamp, double dx = 0) {
    PoseCommand c = at(kRest.position + Vec3(dx, 0, 0), stamp);
    c.source = who;
    return c;
  };
  ASSERT_TRUE(g.admit(0, from("/robot_a", 0.0), 0.0).accepted);
  EXPECT_EQ(g.owner(0), "/robot_a");
  const Admission b = g.admit(0, from("/robot_b", 0.1, 0.001), 0.1);
  EXPECT_FALSE(b.accepted);
  EXPECT_EQ(b.rule, GuardRule::Owner);
  EXPECT_NE(b.reason.find("/robot_a"), std::string::npos) << b.reason;
  EXPECT_NE(b.reason.find("/robot_b"), std::string::npos) << b.reason;
  EXPECT_TRUE(g.admit(0, from("/robot_a", 0.2), 0.2).accepted);
  // A command of the owner that another rule rejects still shows it is not silent.
  EXPECT_EQ(g.admit(0, from("/robot_a", 0.1), 0.3).rule, GuardRule::OutOfOrder);
  EXPECT_EQ(g.admit(0, from("/robot_b", 0.75), 0.75).rule, GuardRule::Owner);  // 0.45 s silent
  // Silent for more than the timeout: the next source takes the needle.
  ASSERT_TRUE(g.admit(0, from("/robot_b", 0.81), 0.81).accepted);
  EXPECT_EQ(g.owner(0), "/robot_b");
  EXPECT_EQ(g.admit(0, from("/robot_a", 0.82), 0.82).rule, GuardRule::Owner);
  EXPECT_EQ(g.count(GuardRule::Owner), 3u);
  // An explicit holder (the ~insert action) is refused while /robot_b commands, takes the
  // needle once it is silent, and keeps it, silent or not, until it releases it.
  std::string why;
  EXPECT_FALSE(g.hold(0, "~insert", 1.0, why));
  EXPECT_NE(why.find("/robot_b"), std::string::npos) << why;
  ASSERT_TRUE(g.hold(0, "~insert", 1.4, why));
  const Admission held = g.admit(0, from("/robot_b", 5.0), 5.0);
  EXPECT_EQ(held.rule, GuardRule::Owner);
  EXPECT_NE(held.reason.find("held by ~insert"), std::string::npos) << held.reason;
  EXPECT_FALSE(g.mayCommand(0, "/planner", 5.0, why));
  g.release(0, "/robot_b");  // not the holder: nothing
  EXPECT_EQ(g.owner(0), "~insert");
  g.release(0, "~insert");
  EXPECT_EQ(g.owner(0), "");
  // A plan keeps the needle until its end, however long its sender is silent, and the
  // timeout after it.
  ASSERT_TRUE(g.mayCommand(0, "/planner", 5.1, why));
  g.own(0, "/planner", 5.1, 8.0);
  EXPECT_EQ(g.admit(0, from("/robot_b", 7.9), 7.9).rule, GuardRule::Owner);
  EXPECT_EQ(g.admit(0, from("/robot_b", 8.4), 8.4).rule, GuardRule::Owner);
  EXPECT_TRUE(g.admit(0, from("/robot_b", 8.61), 8.61).accepted);
  EXPECT_EQ(g.count(GuardRule::Owner), 8u);
  // Unnamed commands are not arbitrated (a consumer with one source); restart() frees all.
  EXPECT_TRUE(g.admit(0, at(kRest.position, 8.7), 8.7).accepted);
  g.restart();
  EXPECT_EQ(g.owner(0), "");
  EXPECT_TRUE(g.admit(0, from("/robot_a", 0.0), 0.0).accepted);
}

// Issue #39: the guard sees the base, not the tip. The tip's speed is measured every step
// from the needle states (sim/tip_speed.hpp), the same figure live and predicted: in free
// space before the tissue the tip moves with the base (10 mm/s); a prediction at the live
// step reports the live run's largest tip speed, and when.
TEST(TipSpeed, TheTipMovesWithTheBaseInFreeSpaceAndPredictionAndLiveRunAgree) {
  const Scene sc = loadScene(std::string(NEEDLE_SIM_SOURCE_DIR) + "/config/scenes/phantom_insertion_8x4x4.yaml");
  Simulation live(sc);
  const BasePose start = live.needle(0).trajectory().pose(0.0);
  BasePose end = start;
  end.position += 0.005 * start.direction;  // 5 mm in 0.5 s: the tip (3 mm out) punctures at 0.3 s
  InsertionPlan plan;
  plan.waypoints = {{0.5, end}};
  plan.duration = 0.5;
  plan.dt = sc.dt;
  const Prediction p = predictInsertion(live, plan);
  live.needle(0).trajectory().replaceFrom(0.0, sc.dt, plan.waypoints);
  TipSpeedMeter meter;
  meter.observe(live);
  EXPECT_EQ(meter.speed(0), 0.0);  // nothing measured yet
  double largest = 0, at = 0;
  for (int k = 1; k <= 500; ++k) {
    const Vec3 before = live.needle(0).tipPosition();
    live.step();
    meter.observe(live);
    // The meter's figure is the tip's displacement over the step.
    ASSERT_NEAR(meter.speed(0), (live.needle(0).tipPosition() - before).norm() / sc.dt, 1e-12);
    if (k >= 50 && k <= 250) {
      EXPECT_NEAR(meter.speed(0), 0.01, 1e-4) << "step " << k << ": in free space";
    }
    if (meter.speed(0) > largest) largest = meter.speed(0), at = live.time();
  }
  EXPECT_DOUBLE_EQ(meter.largest(0), largest);
  EXPECT_DOUBLE_EQ(meter.largestAt(0), at);
  EXPECT_GT(largest, 0.015) << "the puncture pushes the tip ahead of the base";
  EXPECT_NEAR(p.max_tip_speed, largest, 1e-9 * largest);
  EXPECT_NEAR(p.max_tip_speed_t, at, 1e-9);
  // reset(): the next observation measures nothing.
  meter.reset();
  meter.observe(live);
  EXPECT_EQ(meter.speed(0), 0.0);
  EXPECT_EQ(meter.largest(0), 0.0);
}

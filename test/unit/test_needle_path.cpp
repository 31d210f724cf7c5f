// Steering building blocks (issue #19): duty-cycled spinning expanded into base keyframes,
// the cut path's measures (length, end curvature, circle fit), and the cut path a straight
// symmetric insertion leaves (no lateral drift).
#include <gtest/gtest.h>

#include <cmath>

#include "needle_sim/needle/base_trajectory.hpp"
#include "needle_sim/needle/duty_cycled_spin.hpp"
#include "needle_sim/needle/tip_path.hpp"
#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/sim/simulation.hpp"

using namespace needle_sim;

namespace {
NeedleMotionKey key(double t, double x, double roll = 0, double rate = 0, double duty = 0) {
  NeedleMotionKey k;
  k.t = t;
  k.position = Vec3(x, 0, 0);
  k.roll = roll;
  k.spin_rate = rate;
  k.spin_duty = duty;
  return k;
}
}  // namespace

// Two turns in a 4 s segment at 1 turn/s and duty 0.5: each 2 s cycle turns 2 pi in its first
// second, then holds; the position advances as the segment's; the next key keeps its roll
// plus the 4 pi turned, so the base never unwinds.
TEST(DutyCycledSpin, WholeTurnsTheDutyFractionOfTheTime) {
  const BasePose rest{Vec3::Zero(), Vec3::UnitX(), 0.0};
  const auto keys = expandDutyCycledSpin({key(0, 0, 0.3, 2 * M_PI, 0.5), key(4, 0.04, 0.3), key(5, 0.05, 0.3)}, rest);
  BaseTrajectory tr(rest);
  for (const auto& k : keys) {
    EXPECT_EQ(k.spin_duty, 0.0);
    tr.add(k.t, BasePose{k.position, k.direction, k.roll});
  }
  for (double t = 0; t <= 5.0; t += 0.01) {
    const BasePose p = tr.pose(t);
    EXPECT_NEAR(p.position.x(), 0.01 * t, 1e-12) << t;  // the advance is untouched
    const double c = std::min(std::floor(t / 2), 1.0);   // completed cycles (2 in 4 s)
    const double in = std::min(t - 2 * c, 1.0);           // time turned in this cycle
    const double expected = t >= 4 ? 0.3 + 4 * M_PI : 0.3 + 2 * M_PI * c + 2 * M_PI * in;
    EXPECT_NEAR(p.roll, expected, 1e-9) << t;
  }
  // Duty 1: continuous turning at the rate (rounded to whole turns); duty 0: nothing added.
  const auto full = expandDutyCycledSpin({key(0, 0, 0, 2 * M_PI, 1.0), key(3, 0.03)}, rest);
  EXPECT_NEAR(full.back().roll, 6 * M_PI, 1e-12);
  EXPECT_EQ(expandDutyCycledSpin({key(0, 0), key(3, 0.03)}, rest).size(), 2u);
}

TEST(DutyCycledSpin, RefusesBadInput) {
  const BasePose rest;
  EXPECT_THROW(expandDutyCycledSpin({key(0, 0, 0, 1, 1.5), key(1, 0)}, rest), std::invalid_argument);
  EXPECT_THROW(expandDutyCycledSpin({key(0, 0, 0, 1, -0.1), key(1, 0)}, rest), std::invalid_argument);
  EXPECT_THROW(expandDutyCycledSpin({key(0, 0, 0, -1, 0.5), key(1, 0)}, rest), std::invalid_argument);
  EXPECT_THROW(expandDutyCycledSpin({key(0, 0, 0, 0, 0.5), key(1, 0)}, rest), std::invalid_argument);
  EXPECT_THROW(expandDutyCycledSpin({key(0, 0, 0, NAN, 0.5), key(1, 0)}, rest), std::invalid_argument);
}

// Points every 0.25 mm on an arc of radius 80 mm in a tilted plane: the fit finds the radius,
// the centre and the plane; the end curvature over 5 mm is 1/R; a straight line has ~0.
TEST(TipPath, CircleFitAndEndCurvatureOfAnArc) {
  const double R = 0.08;
  const Vec3 c(0.01, -0.02, 0.03);
  const Vec3 e1 = Vec3(1, 1, 0).normalized(), e2 = Vec3(-1, 1, 2).normalized();  // orthonormal
  ASSERT_NEAR(e1.dot(e2), 0, 1e-15);
  std::vector<Vec3> arc;
  for (int i = 0; i <= 200; ++i) {
    const double a = 0.25e-3 * i / R;
    arc.push_back(c + R * (std::cos(a) * e1 + std::sin(a) * e2));
  }
  EXPECT_NEAR(pathLength(arc), 0.05, 0.05 * 1e-6);
  const CircleFit f = fitCircle(arc);
  ASSERT_TRUE(f.ok);
  EXPECT_NEAR(f.radius, R, 1e-9);
  EXPECT_LT((f.centre - c).norm(), 1e-9);
  EXPECT_NEAR(std::abs(f.normal.dot(e1.cross(e2))), 1.0, 1e-12);
  EXPECT_LT(f.rms_residual, 1e-12);
  EXPECT_LT(f.rms_out_of_plane, 1e-12);
  EXPECT_NEAR(endCurvature(arc, 5e-3), 1 / R, 1e-4 / R);
  EXPECT_TRUE(std::isnan(endCurvature(arc, 0.06)));  // longer than the path
  const auto stretch = pathStretch(arc, 0.01, 0.02);
  EXPECT_NEAR(pathLength(stretch), 0.01, 1e-8);
  std::vector<Vec3> line;
  for (int i = 0; i <= 100; ++i) line.push_back(Vec3(1e-3 * i, 0.01, 0.01));
  EXPECT_LT(endCurvature(line, 5e-3), 1e-9);
}

// The paper's phantom, straight insertion with the symmetric tip: the cut path starts at the
// puncture point on the left face, runs along the needle's axis to the tip's last anchor, and
// does not drift sideways.
TEST(TipPath, StraightSymmetricInsertionCutsAStraightPath) {
  Simulation sim(loadScene(std::string(NEEDLE_SIM_SOURCE_DIR) + "/config/scenes/phantom_insertion_8x4x4.yaml",
                           {"time.duration=1.5"}));
  for (long k = 0; k < sim.scene().numSteps(); ++k) sim.step();
  const std::vector<Vec3>& path = sim.interaction()->cutPath(0);
  ASSERT_GE(path.size(), 20u);
  EXPECT_NEAR(path.front().x(), 0.0, 1e-9);  // the left face
  double drift = 0;
  for (const Vec3& p : path) drift = std::max(drift, std::hypot(p.y() - 0.01, p.z() - 0.01));
  EXPECT_LT(drift, 1e-9);
  // The path reaches the tip (rest space; the tissue ahead of the tip is pushed by less than
  // the 1 mm shaft spacing), and its points are at most a quarter spacing apart.
  EXPECT_NEAR(path.back().x(), sim.needle(0).tipPosition().x(), 1e-3);
  EXPECT_GT(path.back().x(), 0.01);
  for (size_t i = 1; i < path.size(); ++i) EXPECT_LE((path[i] - path[i - 1]).norm(), 0.25e-3 + 0.05e-3);
}

// Through the beam: a steel needle in free space spun by its base (one turn in the first
// second of each 2 s cycle) turns its tip with it (torsion is stiff: the tip frame follows
// the base's roll to a small lag) and ends each cycle at the commanded roll.
TEST(DutyCycledSpin, TheTipFollowsTheSpunBase) {
  Simulation sim(loadScene(std::string(NEEDLE_SIM_SOURCE_DIR) + "/config/scenes/needle_free_motion.yaml",
                           {"needle.gravity=[0,0,0]", "time.duration=4.5",
                            "needle.motion=[{t: 0, advance: 0, spin: {rate: 6.283185307179586, duty: 0.5}}, "
                            "{t: 4, advance: 0.02}]"}));
  auto rollOf = [](const Eigen::Quaterniond& q) {
    const Vec3 y = q * Vec3::UnitY();  // the needle stays along x: its frame's y turns in the y-z plane
    return std::atan2(y.z(), y.y());
  };
  double worst = 0;
  for (long k = 0; k < sim.scene().numSteps(); ++k) {
    sim.step();
    const double t = sim.time();
    const BasePose cmd = sim.needle(0).trajectory().pose(t);
    const int tip = sim.needle(0).beam().numNodes() - 1;
    const double tip_roll = rollOf(sim.needle(0).state().q[tip]);
    worst = std::max(worst, std::abs(std::remainder(tip_roll - cmd.roll, 2 * M_PI)));
    if (std::abs(t - 1.5) < 1e-9) {
      EXPECT_NEAR(std::remainder(cmd.roll, 2 * M_PI), 0.0, 1e-9);  // holding after a turn
    }
    if (std::abs(t - 0.25) < 1e-9) {
      EXPECT_NEAR(cmd.roll, M_PI / 2, 1e-9);  // a quarter turn in
    }
  }
  EXPECT_LT(worst, 0.02);  // radians
  EXPECT_NEAR(sim.needle(0).trajectory().pose(4.5).roll, 4 * M_PI, 1e-9);
}

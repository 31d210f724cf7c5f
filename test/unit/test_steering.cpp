// Steering a bevel tip to a target on the simulator's own prediction
// (steer/steering_planner.hpp, doc/method.md "Steering to a target").
#include <gtest/gtest.h>

#include <string>

#include "needle_sim/core/error.hpp"
#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/steer/steering_planner.hpp"

using namespace needle_sim;

namespace {
const std::string kPhantom = std::string(NEEDLE_SIM_SOURCE_DIR) + "/config/scenes/phantom_insertion_8x4x4.yaml";
}

// A target 0.1 mm below the axis at 18 mm: the full arc (bevel turned down) overshoots it,
// so the plan flips; the planner's predicted tip is within 20 um, and the plan run on the
// live simulation (same time step) ends where it was predicted.
TEST(Steering, RollFlipPlanReachesAnOffAxisTargetAndTheLiveRunAgrees) {
  Simulation sim(loadScene(kPhantom, {"needle.bevel.angle=0.5235987755982988", "interaction.shaft_spacing=0.0005"}));
  SteeringRequest req;
  req.target = Vec3(0.018, 0.0099, 0.0100);
  req.tolerance = 2e-5;
  const SteeringPlan plan = planSteering(sim, req);
  EXPECT_TRUE(plan.reached);
  EXPECT_LT(plan.distance, 2e-5);
  EXPECT_LT(plan.flip_depth, plan.advance);  // an S, not the full arc
  EXPECT_NEAR(std::remainder(plan.roll, 2 * M_PI), M_PI, 0.05);  // the bevel turned towards -y
  EXPECT_LE(static_cast<int>(plan.iterations.size()), req.max_predictions);
  // The flip-depth iterates start from the full arc's checkpoints (the same roll: this scene
  // is symmetric about the bevel's plane), so they simulate fewer steps than it.
  ASSERT_GE(plan.iterations.size(), 2u);
  for (size_t i = 1; i < plan.iterations.size(); ++i) {
    EXPECT_GT(plan.iterations[i].resumed_at, 0.0) << "prediction " << i + 1;
    EXPECT_LT(plan.iterations[i].steps_run, plan.iterations[0].steps_run) << "prediction " << i + 1;
  }
  const double now = sim.time(), end = plan.plan.waypoints.back().first;
  sim.needle(0).trajectory().replaceFrom(now, sim.dt(), plan.plan.waypoints);
  while (sim.time() - now < end - 1e-9 * sim.dt()) sim.step();
  EXPECT_LT((sim.needle(0).tipPosition() - plan.tip).norm(), 1e-9);
}

// Requests that cannot be planned fail before any prediction, naming what is wrong.
TEST(Steering, RefusesWhatItCannotPlan) {
  Simulation bevel(loadScene(kPhantom, {"needle.bevel.angle=0.5"}));
  Simulation symmetric(loadScene(kPhantom));
  auto key = [](const Simulation& s, const Vec3& target, double speed = 0.01, int predictions = 8, long steps = 1000000) {
    SteeringRequest r;
    r.target = target;
    r.speed = speed;
    r.max_predictions = predictions;
    r.max_steps = steps;
    try {
      planSteering(s, r);
    } catch (const InputError& e) {
      return e.key();
    }
    return std::string("none");
  };
  EXPECT_EQ(key(symmetric, Vec3(0.018, 0.01, 0.01)), "steer.needle");
  EXPECT_EQ(key(bevel, Vec3(0.05, 0.01, 0.01)), "steer.target");   // beyond the 40 mm block
  EXPECT_EQ(key(bevel, Vec3(-0.01, 0.01, 0.01)), "steer.target");  // outside, behind the entry face
  EXPECT_EQ(key(bevel, Vec3(0.018, 0.01, 0.01), 0), "steer.speed");
  EXPECT_EQ(key(bevel, Vec3(0.018, 0.01, 0.01), 0.01, 101), "steer.max_predictions");
  // A request whose predictions would run too long is refused before it runs (1 um/s: 18,000 s).
  EXPECT_EQ(key(bevel, Vec3(0.018, 0.01, 0.01), 1e-6, 8, 100000).rfind("predict.", 0), 0u);
}

// One budget for the whole plan (the node's ~steer under ~predict_max_wall): every
// prediction of the search checks it.
TEST(Steering, ItsBudgetStopsThePlanning) {
  Simulation sim(loadScene(kPhantom, {"needle.bevel.angle=0.5235987755982988"}));
  SteeringRequest req;
  req.target = Vec3(0.018, 0.0099, 0.0100);
  int checks = 0;
  req.budget.cancelled = [&checks] { return ++checks > 50; };  // within the first prediction
  try {
    planSteering(sim, req);
    ADD_FAILURE() << "not stopped";
  } catch (const PredictionStopped& e) {
    EXPECT_NE(std::string(e.what()).find("cancelled"), std::string::npos) << e.what();
  }
  EXPECT_EQ(checks, 51);
}

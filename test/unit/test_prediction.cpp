// Copying a simulation and predicting an insertion plan on the copy (the ROS `predict`
// service's core): a copy continues exactly as the original would, bit for bit, through
// contact events and mesh changes; stepping it leaves the original alone; a prediction at
// the live time step is the live run of the same plan; a coarser prediction step agrees
// with the live step; a prediction resumed from another's checkpoint is the whole prediction;
// bad plans are refused before any work.
#include <gtest/gtest.h>

#include <chrono>

#include <cmath>
#include <limits>
#include <string>

#include "needle_sim/core/blas_threads.hpp"
#include "needle_sim/core/error.hpp"
#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/sim/prediction.hpp"
#include "needle_sim/sim/simulation.hpp"

using namespace needle_sim;

namespace {
const std::string kScenes = std::string(NEEDLE_SIM_SOURCE_DIR) + "/config/scenes/";

// Largest difference of any state entry of two simulations (infinity if their meshes or
// steps differ).
double stateDifference(const Simulation& a, const Simulation& b) {
  const double inf = std::numeric_limits<double>::infinity();
  if (a.stepIndex() != b.stepIndex() || a.time() != b.time() || a.numDofs() != b.numDofs()) return inf;
  double d = 0;
  if (a.hasTissue()) {
    d = std::max(d, (a.tissue().positions() - b.tissue().positions()).lpNorm<Eigen::Infinity>());
    d = std::max(d, (a.tissue().velocities() - b.tissue().velocities()).lpNorm<Eigen::Infinity>());
  }
  for (int n = 0; n < a.numNeedles(); ++n) {
    const auto &sa = a.needle(n).state(), &sb = b.needle(n).state();
    for (size_t i = 0; i < sa.p.size(); ++i) {
      d = std::max(d, (sa.p[i] - sb.p[i]).lpNorm<Eigen::Infinity>());
      d = std::max(d, (sa.q[i].coeffs() - sb.q[i].coeffs()).lpNorm<Eigen::Infinity>());
    }
    d = std::max(d, (a.needle(n).velocities() - b.needle(n).velocities()).lpNorm<Eigen::Infinity>());
    d = std::max(d, (a.needle(n).baseForce() - b.needle(n).baseForce()).lpNorm<Eigen::Infinity>());
    if (a.interaction() && (a.interaction()->activePoints(n) != b.interaction()->activePoints(n) ||
                            a.interaction()->state(n) != b.interaction()->state(n)))
      return inf;
  }
  return d;
}

InsertionPlan straightPlan(const Simulation& sim, double advance, double over, double duration, double dt) {
  InsertionPlan plan;
  BasePose end = sim.needle(0).trajectory().pose(sim.time());
  end.position += advance * end.direction;
  plan.waypoints = {{over, end}};
  plan.duration = duration;
  plan.dt = dt;
  return plan;
}
}  // namespace

TEST(SimulationCopy, ContinuesExactlyLikeTheOriginalThroughMeshChanges) {
  setBlasThreads(1);
  Simulation sim(loadScene(kScenes + "phantom_insertion_adaptive.yaml"));
  for (int k = 0; k < 600; ++k) sim.step();  // punctured, shaft points laid, mesh refined
  ASSERT_GT(sim.interaction()->activePoints(0), 1);
  Simulation copy(sim);
  EXPECT_EQ(stateDifference(sim, copy), 0.0);
  int changes = 0;
  for (int k = 0; k < 300; ++k) {
    changes += sim.step().mesh_changed;
    copy.step();
    ASSERT_EQ(stateDifference(sim, copy), 0.0) << "step " << sim.stepIndex();
  }
  EXPECT_GT(changes, 0);  // the copies' adaptation ran through a mesh change
  EXPECT_EQ(sim.elementLevels(), copy.elementLevels());
}

TEST(SimulationCopy, CannulaAndElectrodeContinueExactly) {
  setBlasThreads(1);
  Simulation sim(loadScene(kScenes + "phantom_cannula_electrode.yaml"));
  for (int k = 0; k < 1200; ++k) sim.step();  // both inserted, the cannula about to withdraw
  Simulation copy(sim);
  while (sim.time() < sim.scene().duration - 1e-9) {
    sim.step();
    copy.step();
  }
  EXPECT_EQ(stateDifference(sim, copy), 0.0);
  EXPECT_EQ(copy.interaction()->state(1), sim.interaction()->state(1));
  EXPECT_GT(copy.interaction()->activePoints(1), 0);  // the electrode stayed
}

TEST(SimulationCopy, SteppingTheCopyLeavesTheOriginalAlone) {
  Simulation sim(loadScene(kScenes + "phantom_insertion_adaptive.yaml"));
  for (int k = 0; k < 350; ++k) sim.step();
  const VecX x = sim.tissue().positions();
  const Vec3 tip = sim.needle(0).tipPosition();
  const int points = sim.interaction()->activePoints(0), dofs = sim.numDofs();
  const size_t keys = sim.needle(0).trajectory().size();
  {
    Simulation copy(sim);
    copy.needle(0).trajectory().replaceFrom(copy.time(), copy.dt(), {{0.5, BasePose{tip, Vec3::UnitX(), 0}}});
    for (int k = 0; k < 300; ++k) copy.step();
    ASSERT_GT((copy.needle(0).tipPosition() - tip).norm(), 1e-3);
  }
  EXPECT_EQ(sim.stepIndex(), 350);
  EXPECT_EQ(sim.numDofs(), dofs);
  EXPECT_EQ((sim.tissue().positions() - x).lpNorm<Eigen::Infinity>(), 0.0);
  EXPECT_EQ(sim.needle(0).tipPosition(), tip);
  EXPECT_EQ(sim.interaction()->activePoints(0), points);
  EXPECT_EQ(sim.needle(0).trajectory().size(), keys);
  sim.step();  // and it still steps (its factors and bindings are its own)
}

TEST(SimulationCopy, TimeStepChangeKeepsTheClock) {
  Simulation sim(loadScene(kScenes + "phantom_insertion_8x4x4.yaml"));
  for (int k = 0; k < 10; ++k) sim.step();
  EXPECT_NEAR(sim.time(), 0.010, 1e-15);
  sim.setTimeStep(0.004);
  EXPECT_NEAR(sim.time(), 0.010, 1e-15);
  sim.step();
  sim.step();
  EXPECT_NEAR(sim.time(), 0.018, 1e-15);
  EXPECT_EQ(sim.stepIndex(), 12);
  EXPECT_THROW(sim.setTimeStep(0.0), std::invalid_argument);
  EXPECT_THROW(sim.setTimeStep(std::nan("")), std::invalid_argument);
}

TEST(Prediction, AtTheLiveStepItIsTheLiveRunOfThePlan) {
  setBlasThreads(1);
  Simulation sim(loadScene(kScenes + "phantom_insertion_adaptive.yaml"));
  sim.setTarget("target", Vec3(0.012, 0.01, 0.0115));
  for (int k = 0; k < 200; ++k) sim.step();
  InsertionPlan plan = straightPlan(sim, 0.01, 0.8, 1.0, 0.0);
  plan.sample_period = 0.1;
  const Prediction p = predictInsertion(sim, plan);
  EXPECT_EQ(sim.stepIndex(), 200);  // untouched
  ASSERT_EQ(p.steps, 1000);
  ASSERT_EQ(p.samples.size(), 11u);  // t = 0, 0.1, ..., 1.0
  EXPECT_NEAR(p.samples.back().t, 1.0, 1e-9);
  // The same plan, live.
  sim.needle(0).trajectory().replaceFrom(sim.time(), sim.dt(), plan.waypoints);
  for (int k = 0; k < 1000; ++k) {
    sim.step();
    if ((k + 1) % 100 == 0) {
      const PredictionSample& s = p.samples[(k + 1) / 100];
      EXPECT_NEAR(s.t, (k + 1) * 0.001, 1e-9);
      EXPECT_EQ(s.tips[0], sim.needle(0).tipPosition()) << "t = " << s.t;
      EXPECT_EQ(s.targets[0], sim.targetPosition(0)) << "t = " << s.t;
      EXPECT_EQ(s.base_forces[0], -sim.needle(0).baseForce()) << "t = " << s.t;
      EXPECT_EQ(s.tip_distances[0], (sim.targetPosition(0) - sim.needle(0).tipPosition()).norm());
    }
  }
  // The plan did what it says: the tip went 10 mm further, the target was pushed along.
  EXPECT_NEAR(p.samples.back().tips[0].x() - p.samples.front().tips[0].x(), 0.01, 2e-4);
  EXPECT_GT((p.samples.back().targets[0] - p.samples.front().targets[0]).norm(), 1e-7);
  EXPECT_LT(p.samples.back().base_forces[0].x(), 0);  // the tissue pushes the needle back onto its holder
}

// On the adaptive scene with the paper's element. On the default one the difference is 1.40 %
// at a 10 ms step and 1.74 % at 5 ms: not the step's own error (it would halve) but the
// adaptivity's schedule, which counts steps (adaptivity.every_steps), so a prediction at
// another step changes its mesh at other times; the step's error on the default element is
// CoarseStepOnAFixedMeshUsesItsOwnCompliance's. For the same reason without the scene's
// refinement ahead of the tip (lookahead 0): the elements it refines depend on when the passes
// run, and with it the two schedules part by 1.75 % (target and force), a mesh difference.
TEST(Prediction, CoarseStepAgreesWithTheLiveStep) {
  setBlasThreads(1);
  Simulation sim(loadScene(kScenes + "phantom_insertion_adaptive.yaml", {"tissue.element=trilinear", "adaptivity.lookahead=0"}));
  sim.setTarget("target", Vec3(0.012, 0.01, 0.0115));
  for (int k = 0; k < 200; ++k) sim.step();
  const Prediction fine = predictInsertion(sim, straightPlan(sim, 0.012, 1.2, 1.5, 0.0));
  const Prediction coarse = predictInsertion(sim, straightPlan(sim, 0.012, 1.2, 1.5, 0.01));
  EXPECT_EQ(coarse.steps, 150);
  const auto &f = fine.samples.back(), &c = coarse.samples.back();
  const double moved = (f.targets[0] - fine.samples.front().targets[0]).norm();
  ASSERT_GT(moved, 1e-7);
  EXPECT_LT((c.targets[0] - f.targets[0]).norm(), 0.01 * moved);
  EXPECT_LT((c.tips[0] - f.tips[0]).norm(), 1e-6);
  EXPECT_LT((c.base_forces[0] - f.base_forces[0]).norm(), 0.01 * f.base_forces[0].norm());
  std::printf("target moved %.3e m; coarse - fine: target %.3e m, tip %.3e m, force %.3e of %.3e N\n", moved,
              (c.targets[0] - f.targets[0]).norm(), (c.tips[0] - f.tips[0]).norm(),
              (c.base_forces[0] - f.base_forces[0]).norm(), f.base_forces[0].norm());
}

// The same on a fixed mesh, where nothing else refactorises: the prediction's first step at
// its own time step must (A = (1 + h alpha) M + (h beta + h^2) K is another matrix, and the
// constraint solve takes the compliance from the factor). With the live step's factor kept,
// the 10x coarser prediction's holder force was 21 % off and its tip 60 um, 28 % of the
// bevel's bend; with its own, 2.3 % and 1.1 % (the coarser step's own error).
TEST(Prediction, CoarseStepOnAFixedMeshUsesItsOwnCompliance) {
  setBlasThreads(1);
  Simulation sim(loadScene(kScenes + "phantom_insertion_8x4x4.yaml", {"needle.bevel.angle=0.5235987755982988"}));
  for (int k = 0; k < 500; ++k) sim.step();  // punctured, 4.5 mm in
  ASSERT_GT(sim.interaction()->activePoints(0), 1);
  const Prediction fine = predictInsertion(sim, straightPlan(sim, 0.012, 1.2, 1.5, 0.0));
  const Prediction coarse = predictInsertion(sim, straightPlan(sim, 0.012, 1.2, 1.5, 0.01));
  const auto &f = fine.samples.back(), &c = coarse.samples.back();
  const double bent = std::hypot(f.tips[0].y() - fine.samples.front().tips[0].y(), f.tips[0].z() - fine.samples.front().tips[0].z());
  std::printf("bevel bend %.3e m; coarse - fine: tip %.3e m, force %.3e of %.3e N\n", bent, (c.tips[0] - f.tips[0]).norm(),
              (c.base_forces[0] - f.base_forces[0]).norm(), f.base_forces[0].norm());
  ASSERT_GT(bent, 1e-5);
  EXPECT_LT((c.tips[0] - f.tips[0]).norm(), 0.05 * bent);
  EXPECT_LT((c.base_forces[0] - f.base_forces[0]).norm(), 0.05 * f.base_forces[0].norm());
}

TEST(Prediction, RefusesBadPlansBeforeAnyWork) {
  Simulation sim(loadScene(kScenes + "phantom_insertion_8x4x4.yaml"));
  for (int k = 0; k < 5; ++k) sim.step();
  const InsertionPlan good = straightPlan(sim, 0.01, 1.0, 0.0, 0.0);
  auto expectKey = [&](InsertionPlan p, const std::string& key, long max_steps = 1000000) {
    try {
      predictInsertion(sim, p, max_steps);
      ADD_FAILURE() << "accepted a plan with a bad " << key;
    } catch (const InputError& e) {
      EXPECT_EQ(e.key(), key) << e.what();
    }
  };
  InsertionPlan p = good;
  p.needle = 1;
  expectKey(p, "predict.needle");
  p = good;
  p.waypoints.push_back(p.waypoints.back());
  expectKey(p, "predict.waypoints[1].time");  // not increasing
  p = good;
  p.waypoints[0].first = std::nan("");
  expectKey(p, "predict.waypoints[0].time");
  p = good;
  p.waypoints[0].second.position.x() = std::numeric_limits<double>::infinity();
  expectKey(p, "predict.waypoints[0].position");
  p = good;
  p.waypoints[0].second.direction = Vec3(0, 0, 0);
  expectKey(p, "predict.waypoints[0].direction");
  p = good;
  p.dt = -0.001;
  expectKey(p, "predict.dt");
  p = good;
  p.waypoints.clear();
  expectKey(p, "predict.duration");  // nothing to simulate
  expectKey(good, "predict.duration", 999);  // 1000 steps over the limit
  EXPECT_EQ(sim.stepIndex(), 5);
  const Prediction ok = predictInsertion(sim, good);
  EXPECT_EQ(ok.steps, 1000);
  EXPECT_EQ(ok.samples.size(), 1001u);  // every step
}

// Two plans that agree for 0.4 s (4 mm in, then on to 8 mm, or a hold at 4 mm): the second,
// resumed from the first's checkpoint at 0.2 s, is the second predicted from now, to the bit.
// From the one at 0.4 s, where they part, it agrees to rounding (the step that ends at the
// keyframe ends a rounding error after it, where the plans differ by that much); a
// checkpoint from after they part is refused.
TEST(Prediction, ResumedFromACheckpointItIsTheWholePrediction) {
  setBlasThreads(1);
  Simulation sim(loadScene(kScenes + "phantom_insertion_8x4x4.yaml"));
  for (int k = 0; k < 300; ++k) sim.step();  // punctured
  const BasePose p0 = sim.needle(0).trajectory().pose(sim.time());
  auto at = [&](double s) { return BasePose{p0.position + s * p0.direction, p0.direction, p0.roll}; };
  InsertionPlan on, hold;
  on.waypoints = {{0.4, at(0.004)}, {0.8, at(0.008)}};
  hold.waypoints = {{0.4, at(0.004)}, {0.6, at(0.004)}};
  on.duration = hold.duration = 1.0;
  on.sample_period = hold.sample_period = 0.1;
  PredictionReuse keep;
  keep.checkpoint_times = {0.7, 0.2, 0.4};
  const Prediction first = predictInsertion(sim, on, 1000000, keep);
  ASSERT_EQ(first.checkpoints.size(), 3u);
  EXPECT_NEAR(first.checkpoints[0].t, 0.2, 1e-9);
  EXPECT_EQ(first.checkpoints[0].step, 200);
  const Prediction whole = predictInsertion(sim, hold);
  PredictionReuse resume;
  resume.resume = &first.checkpoints[0];
  const Prediction resumed = predictInsertion(sim, hold, 1000000, resume);
  EXPECT_EQ(resumed.steps, 1000);
  EXPECT_EQ(resumed.steps_run, 800);
  ASSERT_EQ(resumed.samples.size(), whole.samples.size());
  for (size_t i = 0; i < whole.samples.size(); ++i) {
    EXPECT_EQ(resumed.samples[i].t, whole.samples[i].t);
    EXPECT_EQ(resumed.samples[i].tips[0], whole.samples[i].tips[0]) << "sample " << i;
    EXPECT_EQ(resumed.samples[i].base_forces[0], whole.samples[i].base_forces[0]) << "sample " << i;
  }
  resume.resume = &first.checkpoints[1];  // at 0.4 s
  const Prediction at_key = predictInsertion(sim, hold, 1000000, resume);
  EXPECT_EQ(at_key.steps_run, 600);
  EXPECT_LT((at_key.samples.back().tips[0] - whole.samples.back().tips[0]).norm(), 1e-12);
  EXPECT_LT((at_key.samples.back().base_forces[0] - whole.samples.back().base_forces[0]).norm(),
            1e-9 * whole.samples.back().base_forces[0].norm());
  // The plans do part after 0.4 s: the hold ends 4 mm short of where going on does.
  EXPECT_NEAR((first.samples.back().tips[0] - whole.samples.back().tips[0]).norm(), 0.004, 2e-4);
  resume.resume = &first.checkpoints[2];  // at 0.7 s, 3 mm apart
  try {
    predictInsertion(sim, hold, 1000000, resume);
    ADD_FAILURE() << "resumed a plan from a checkpoint it does not pass through";
  } catch (const InputError& e) {
    EXPECT_EQ(e.key(), "predict.resume") << e.what();
  }
  EXPECT_EQ(sim.stepIndex(), 300);
}

// A prediction's budget (the node's ~predict_max_wall, ~reset and shutdown): checked before
// every step, it stops the prediction with PredictionStopped naming why, how long it ran and
// how far the plan got; the live simulation is untouched.
TEST(Prediction, ItsBudgetStopsItBeforeAnyStepAfterTheDeadlineOrWhenCancelled) {
  Simulation sim(loadScene(kScenes + "phantom_insertion_8x4x4.yaml"));
  for (int k = 0; k < 5; ++k) sim.step();
  const double live_time = sim.time();
  const InsertionPlan plan = straightPlan(sim, 0.02, 20.0, 0.0, 0.001);  // 20,000 steps: seconds of work
  // Cancelled at the 4th check: exactly 3 steps were run.
  int checks = 0;
  PredictionBudget cancel;
  cancel.cancelled = [&checks] { return ++checks == 4; };
  try {
    predictInsertion(sim, plan, 1000000, {}, cancel);
    ADD_FAILURE() << "not cancelled";
  } catch (const PredictionStopped& e) {
    const std::string m = e.what();
    EXPECT_NE(m.find("cancelled"), std::string::npos) << m;
    EXPECT_NE(m.find("(step 3 of 20000)"), std::string::npos) << m;
  }
  EXPECT_EQ(checks, 4);
  // A deadline already past: not one step.
  PredictionBudget past;
  past.deadline = std::chrono::steady_clock::now();
  past.deadline_name = "the test's deadline";
  try {
    predictInsertion(sim, plan, 1000000, {}, past);
    ADD_FAILURE() << "not stopped";
  } catch (const PredictionStopped& e) {
    const std::string m = e.what();
    EXPECT_NE(m.find("stopped by the test's deadline"), std::string::npos) << m;
    EXPECT_NE(m.find("(step 0 of 20000)"), std::string::npos) << m;
  }
  // 50 ms from now: stopped part way, within a step or so of the deadline.
  PredictionBudget soon;
  soon.deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(50);
  soon.deadline_name = "50 ms";
  const auto t0 = std::chrono::steady_clock::now();
  EXPECT_THROW(predictInsertion(sim, plan, 1000000, {}, soon), PredictionStopped);
  const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  EXPECT_GE(ms, 50.0);
  EXPECT_LT(ms, 1000.0);  // the whole plan takes seconds
  EXPECT_EQ(sim.time(), live_time);
  // Without a budget the same plan is predicted (as far as 100 steps, to keep it short).
  InsertionPlan shorter = plan;
  shorter.duration = 0.1;
  EXPECT_EQ(predictInsertion(sim, shorter, 1000000, {}, {}).steps, 100);
}

// The simulation's parts on their own (include/needle_sim/sim/simulation.hpp lists them):
// the tissue's prepare -> switch, the estimators and their caches, the goal-oriented marking,
// the adaptation schedule, the probes and targets, the state check, the brain-shift pre-step
// on a host of the test's own. Each asserts a known answer (a linear field carried exactly, a
// bound that adds exactly, the steps a pass runs at, the passes a pre-step solves) that the
// part's broken variants would miss.
#include <gtest/gtest.h>

#include <cmath>
#include <string>

#include "needle_sim/brain/brain_shift_prestep.hpp"
#include "needle_sim/command/pose_convention.hpp"
#include "needle_sim/core/error.hpp"
#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/sim/adaptation_passes.hpp"
#include "needle_sim/sim/adaptive_tissue.hpp"
#include "needle_sim/sim/command_pipeline.hpp"
#include "needle_sim/sim/coupled_step.hpp"
#include "needle_sim/sim/simulation.hpp"
#include "needle_sim/sim/target_error_estimator.hpp"
#include "needle_sim/sim/tracked_points.hpp"

using namespace needle_sim;

namespace {
const std::string kScenes = std::string(NEEDLE_SIM_SOURCE_DIR) + "/config/scenes/";

Scene adaptivePhantom(const std::vector<std::string>& more = {}) {
  std::vector<std::string> sets = {"adaptivity={theta: 0.3, max_level: 2}"};
  sets.insert(sets.end(), more.begin(), more.end());
  return loadScene(kScenes + "phantom_8x4x4.yaml", sets);
}

// x = X + A X + b at every node of the body's mesh.
VecX linearField(const HexMesh& mesh) {
  Mat3 A;
  A << 1e-3, 2e-3, -1e-3, 0.5e-3, -2e-3, 1e-3, 3e-3, 0, 1e-3;
  const Vec3 b(1e-4, -2e-4, 3e-4);
  VecX x = mesh.restPositions();
  for (int i = 0; i < mesh.numNodes(); ++i) x.segment<3>(3 * i) += A * x.segment<3>(3 * i) + b;
  return x;
}
}  // namespace

TEST(AdaptiveTissue, SwitchCarriesTheStateOfTheSwitchAndTellsItsDependents) {
  const Scene scene = adaptivePhantom({"tissue.dirichlet=[]"});
  AdaptiveTissue tissue(scene);
  int switches = 0;
  int located = -1;
  tissue.setOnSwitch([&](AdaptiveTissue::Switch& s) {
    ++switches;
    EmbeddedPoint ep;
    located = s.locator.locate(Vec3(0.0101, 0.0101, 0.0101), ep) ? ep.element : -1;
    EXPECT_EQ(&s.body, &tissue.body());
  });
  // A change prepared from the state at rest ...
  MeshAdaptation& forest = *tissue.adaptation();
  ASSERT_TRUE(forest.refineElements({0, 5, 17}).changed);
  const VecX rest_x = forest.transfer(tissue.body().positions());
  auto prepared = tissue.prepare(tissue.forestMesh(forest), rest_x, VecX::Zero(rest_x.size()), true);
  // ... and switched to after the old body moved on: the switch carries the state of now.
  const VecX x = linearField(tissue.body().mesh());
  tissue.body().setState(x, VecX::Constant(x.size(), 0.25));
  const int old_dofs = tissue.body().mesh().numDofs();
  tissue.switchTo(*prepared, true, true);
  const HexMesh& mesh = tissue.body().mesh();
  EXPECT_GT(mesh.numDofs(), old_dofs);
  EXPECT_EQ(switches, 1);
  EXPECT_GE(located, 0);
  const VecX expected = linearField(mesh);  // refinement moves no material: a linear field is exact
  EXPECT_LT((tissue.body().positions() - expected).lpNorm<Eigen::Infinity>(), 1e-15);
  EXPECT_LT((tissue.body().velocities().array() - 0.25).abs().maxCoeff(), 1e-15);
  EXPECT_EQ(static_cast<int>(tissue.levels().size()), mesh.numElements());
  EXPECT_NE(tissue.takeRetired(), nullptr);  // the replaced body, to be freed off the stepping thread
}

TEST(AdaptiveTissue, TheForestIsTheBackgroundPassesWhileLent) {
  const Scene scene = adaptivePhantom();
  AdaptiveTissue tissue(scene);
  tissue.lend();
  EXPECT_THROW(tissue.adaptation(), std::logic_error);
  EXPECT_NO_THROW(tissue.adaptationOfPass());
  tissue.giveBack();
  EXPECT_NE(tissue.adaptation(), nullptr);
}

TEST(EnergyErrorEstimator, KeepsItsEstimateUntilResetAndAnAdoptedOneIsNotCurrent) {
  const Scene scene = adaptivePhantom({"tissue.dirichlet=[]"});
  AdaptiveTissue tissue(scene);
  tissue.body().setState(linearField(tissue.body().mesh()), VecX::Zero(tissue.body().mesh().numDofs()));
  EnergyErrorEstimator energy(&tissue.body(), &tissue.reference());
  EXPECT_EQ(energy.last(), nullptr);
  const double linear = energy.localErrors().global;  // SPR recovers a linear field's stress exactly
  EXPECT_LT(linear, 1e-9 * energy.localErrors().energy);
  // A field SPR cannot recover: the cached estimate stays until reset.
  VecX x = tissue.body().positions();
  for (int i = 0; i < tissue.body().mesh().numNodes(); ++i) x[3 * i + 2] += 1e-4 * std::pow(x[3 * i] / 0.04, 3);
  tissue.body().setState(x, VecX::Zero(x.size()));
  EXPECT_EQ(energy.localErrors().global, linear);
  energy.reset();
  EXPECT_EQ(energy.current(), nullptr);
  const double cubic = energy.localErrors().global;
  EXPECT_GT(cubic, 1e3 * linear + 1e-12);
  EXPECT_EQ(cubic, SprEstimator(tissue.body().model()).estimate(x).global);
  // A background pass's estimate (of another step) becomes the last, not the current one.
  energy.reset();
  ErrorEstimate other;
  other.global = 42;
  energy.adopt(other);
  EXPECT_EQ(energy.last()->global, 42);
  EXPECT_EQ(energy.current(), nullptr);
  // While lent, a stale estimate is a broken wait protocol.
  energy.lend();
  EXPECT_THROW(energy.localErrors(), std::logic_error);
  energy.giveBack();
  EXPECT_EQ(energy.localErrors().global, cubic);
}

TEST(TargetErrorEstimator, CachedPerStepAndTheShiftsErrorAddsExactly) {
  Scene scene = loadScene(kScenes + "phantom_8x4x4.yaml", {"targets=[{name: a, point: [0.02, 0.012, 0.011]}]"});
  Simulation sim(scene);
  for (int k = 0; k < 5; ++k) sim.step();  // gravity: a displacement to estimate
  TissueBody& body = sim.tissue();
  EnergyErrorEstimator energy(&body, nullptr);
  TrackedPoints points(scene, nullptr);
  points.embed(PointLocator(body.mesh()));
  const VecX shifted = body.mesh().restPositions();
  TargetErrorEstimator estimator(1e-3);
  const TargetErrorState at5{body, energy, &shifted, points, 5};
  const TargetError e0 = estimator.of(0, at5);
  ASSERT_TRUE(e0.valid);
  EXPECT_GT(e0.bound, 0);
  EXPECT_EQ(estimator.lastStep(), 5);
  // Cached by step: a state changed behind its back is not seen until the next step.
  const VecX x = body.positions();
  body.setState(x + VecX::Constant(x.size(), 1e-5), body.velocities());
  EXPECT_EQ(estimator.of(0, at5).bound, e0.bound);
  body.setState(x, body.velocities());
  // The shift's own error adds to the bound, the estimate and the displacement, exactly.
  TargetError shift;
  shift.valid = true;
  shift.bound = 1e-3;
  shift.estimate = Vec3(1e-4, 2e-4, 3e-4);
  shift.component_bound = Vec3(1e-4, 1e-4, 1e-4);
  shift.qoi = Vec3(0, -6.5e-3, 0);
  estimator.setShiftErrors({shift});
  estimator.forget();  // (the duals start from zero again: the same solve as e0's)
  const TargetError e1 = estimator.of(0, {body, energy, &shifted, points, 6});
  EXPECT_EQ(e1.bound, e0.bound + 1e-3);
  EXPECT_EQ(e1.estimate, e0.estimate + shift.estimate);
  EXPECT_EQ(e1.qoi, e0.qoi + shift.qoi);
  // Without a shifted state there is no shift to add.
  estimator.forget();
  EXPECT_NEAR(estimator.of(0, {body, energy, nullptr, points, 7}).bound, e0.bound, 1e-9 * e0.bound);
  EXPECT_DOUBLE_EQ(estimator.radius(0, points), 1e-3);  // the scene gives none
}

TEST(GoalErrorEstimator, RefinesOnlyWhileATargetIsAboveTheTolerance) {
  const Scene scene = adaptivePhantom({"tissue.dirichlet=[]"});
  AdaptiveTissue tissue(scene);
  VecX x = tissue.body().positions();
  for (int i = 0; i < tissue.body().mesh().numNodes(); ++i) x[3 * i + 2] += 1e-4 * std::pow(x[3 * i] / 0.04, 3);
  tissue.body().setState(x, VecX::Zero(x.size()));
  EnergyErrorEstimator energy(&tissue.body(), nullptr);
  const int n = tissue.body().mesh().numElements();
  std::vector<TargetError> errors(2);
  for (auto& e : errors) {
    e.valid = true;
    e.indicator.assign(n, 0.0);
  }
  errors[0].bound = 0.5e-6;
  errors[0].indicator[3] = 2e-7;
  errors[1].bound = 0.9e-6;
  errors[1].indicator[7] = 4e-7;
  GoalErrorEstimator goal(energy, [&](int t) -> const TargetError& { return errors[t]; }, {0, 1}, 1e-6);
  const ErrorEstimate& g = goal.localErrors();
  EXPECT_FALSE(goal.refinementWanted());
  EXPECT_DOUBLE_EQ(g.eta[3], 0.2);
  EXPECT_DOUBLE_EQ(g.eta[7], 0.4);
  EXPECT_DOUBLE_EQ(g.max, 0.4);
  EXPECT_DOUBLE_EQ(g.global, std::sqrt(0.2 * 0.2 + 0.4 * 0.4));
  errors[1].bound = 1.1e-6;
  goal.localErrors();
  EXPECT_TRUE(goal.refinementWanted());
  // A failed estimate: the energy estimate's pattern, normalised, and refinement.
  errors[1].bound = 0;
  errors[0].valid = false;
  const ErrorEstimate& f = goal.localErrors();
  EXPECT_TRUE(goal.refinementWanted());
  const ErrorEstimate& est = energy.localErrors();
  EXPECT_DOUBLE_EQ(f.eta[0], est.eta[0] / est.max);
  EXPECT_DOUBLE_EQ(f.eta[7], est.eta[7] / est.max + 0.4);
}

TEST(AdaptationPasses, RunEveryNStepsAndAtOnceOnAContactEvent) {
  const Scene scene = adaptivePhantom({"adaptivity.every_steps=5"});
  AdaptiveTissue tissue(scene);
  EnergyErrorEstimator energy(&tissue.body(), &tissue.reference());
  AdaptationPasses passes(*scene.adaptivity, tissue, energy, energy, false, [] { return std::vector<Vec3>{}; });
  std::vector<long> adapted;
  for (long k = 1; k <= 12; ++k) {
    StepStats stats;
    const long signature = k >= 7 ? 1 : 0;  // a new constraint point at step 7
    energy.reset();
    passes.afterStep({k, 0, 1e-3}, signature, 0, true, stats);
    if (stats.adapted) adapted.push_back(k);
  }
  EXPECT_EQ(adapted, (std::vector<long>{5, 7, 10}));
  // The period counts from the step dt last changed at.
  std::vector<long> later;
  for (long k = 13; k <= 20; ++k) {
    StepStats stats;
    passes.afterStep({k, 12, 2e-3}, 1, 0, true, stats);
    if (stats.adapted) later.push_back(k);
  }
  EXPECT_EQ(later, (std::vector<long>{17}));
}

TEST(TrackedPoints, NamesTheKeyOfAPointOutsideAndLeavesTargetsAsTheyWereOnARefusal) {
  Scene scene = loadScene(kScenes + "phantom_8x4x4.yaml",
                          {"targets=[{name: a, point: [0.02, 0.01, 0.01], radius: 0.002}]", "probes.1.point=[0.05,0,0]"});
  const HexMesh mesh = buildTissueMesh(scene.tissue);
  TrackedPoints points(scene, nullptr);
  try {
    points.embed(PointLocator(mesh));
    FAIL() << "a probe outside the tissue was embedded";
  } catch (const InputError& e) {
    EXPECT_EQ(e.key(), "probes[1].point");
  }
  scene = loadScene(kScenes + "phantom_8x4x4.yaml", {"targets=[{name: a, point: [0.02, 0.01, 0.01], radius: 0.002}]"});
  TrackedPoints ok(scene, nullptr);
  ok.embed(PointLocator(mesh));
  EXPECT_THROW(ok.setTarget("b", Vec3(0.1, 0, 0), mesh), InputError);
  EXPECT_EQ(ok.numTargets(), 1);
  EXPECT_EQ(ok.setTarget("b", Vec3(0.01, 0.01, 0.01), mesh), 1);
  EXPECT_EQ(ok.setTarget("a", Vec3(0.03, 0.01, 0.01), mesh), 0);  // moved: now a run-time target
  EXPECT_EQ(ok.target(0).planned, Vec3(0.03, 0.01, 0.01));
  EXPECT_EQ(ok.target(0).scene_index, -1);
  EXPECT_DOUBLE_EQ(ok.radius(0, 7e-4), 7e-4);
  TrackedPoints fresh(scene, nullptr);
  EXPECT_DOUBLE_EQ(fresh.radius(0, 7e-4), 0.002);
}

TEST(CoupledStep, TheCheckRefusesNonFiniteAndDivergedStates) {
  const Scene scene = loadScene(kScenes + "phantom_8x4x4.yaml");
  AdaptiveTissue tissue(scene);
  std::vector<std::unique_ptr<NeedleBody>> needles;
  TissueBody& body = tissue.body();
  EXPECT_NO_THROW(checkBodies(&body, needles, 3, 0.05));
  VecX x = body.positions();
  x[10] += 0.4;  // 8 times the size: not yet diverged
  body.setState(x, VecX::Zero(x.size()));
  EXPECT_NO_THROW(checkBodies(&body, needles, 3, 0.05));
  x[10] += 0.2;  // 12 times
  body.setState(x, VecX::Zero(x.size()));
  try {
    checkBodies(&body, needles, 3, 0.05);
    FAIL() << "a diverged state passed";
  } catch (const NumericalError& e) {
    EXPECT_EQ(e.step(), 3);
  }
  x[10] = std::nan("");
  body.setState(x, VecX::Zero(x.size()));
  EXPECT_THROW(checkBodies(&body, needles, 4, 0.05), NumericalError);
}

namespace {
// The phantom as a pre-step host: a target at the block's free end, no adaptivity (or a fake
// one that says the mesh changed on its first pass).
class BoxHost : public PreStepTissue {
 public:
  BoxHost(const Scene& scene, bool adaptive) : tissue_(scene), adaptive_(adaptive) {
    PointLocator(tissue_.body().mesh()).locate(Vec3(0.005, 0.01, 0.01), target_);
  }
  TissueBody& body() override { return tissue_.body(); }
  const EmbeddedSurface* organ() const override { return nullptr; }
  const EmbeddedPoint* target() const override { return &target_; }
  bool adaptive() const override { return adaptive_; }
  bool adapt() override { return ++adapts == 1; }
  void checkState() const override { ++checks; }
  int adapts = 0;
  mutable int checks = 0;

 private:
  AdaptiveTissue tissue_;
  EmbeddedPoint target_;
  bool adaptive_;
};
}  // namespace

TEST(BrainShiftPreStep, ScalesTheLoadToTheTargetShiftAndPassesAsTheMeshAsks) {
  const Scene scene = loadScene(kScenes + "phantom_8x4x4.yaml");
  BrainShiftSettings s;
  s.gravity = Vec3(0, 0, -9.81);
  s.skull_contact = false;
  s.target_shift = 1e-4;
  s.target = "tip";
  const PreStepScene ps{s, scene.tissue, scene.solver, scene.file, nullptr, nullptr};
  for (const bool adaptive : {false, true}) {
    BoxHost host(scene, adaptive);
    std::unique_ptr<BrainShift> shift;
    const BrainShiftResult r = runBrainShiftPreStep(ps, host, shift);
    ASSERT_NE(shift, nullptr);
    const Vec3 u = host.target()->interpolate(host.body().mesh(), host.body().positions()) - host.target()->rest;
    EXPECT_NEAR(u.norm(), 1e-4, 1e-7) << "adaptive " << adaptive;
    EXPECT_NEAR(r.target_displacement.norm(), u.norm(), 1e-12);
    EXPECT_EQ(r.target, "tip");
    // Uniform: one solve; adaptive: a rough pass that changed the mesh, one that did not, the
    // final solve.
    EXPECT_EQ(r.passes, adaptive ? 3 : 1);
    EXPECT_EQ(host.adapts, adaptive ? 2 : 0);
    EXPECT_EQ(host.checks, r.passes);
  }
}

// The command pipeline (sim/command_pipeline.hpp): a command faster than the limit is slowed
// (never jumped to), a plan breaking a limit is refused whole and its sender told, another
// source than the needle's owner is refused, a hold stops the needle; limits lowered while a
// motion is under way slow it.
TEST(CommandPipeline, GuardsEveryWayANeedleIsMoved) {
  Simulation sim(loadScene(kScenes + "phantom_insertion_8x4x4.yaml", {"needle.motion=[]"}));
  CommandLimits limits;  // max_speed 0.05 m/s
  CommandPipeline pipeline(sim, limits);
  const BaseTrajectory& traj = sim.needle(0).trajectory();
  const BasePose rest = traj.rest();
  // 10 mm away, stamped now (asked to be reached at once): followed at the limit, 0.2 s.
  PoseCommand c;
  c.position = rest.position + 0.01 * rest.direction;
  c.orientation = orientationOf(rest, rest);
  c.stamp = 0.0;
  c.source = "robot_a";
  ASSERT_TRUE(pipeline.submit(0, c, 0.0).accepted);
  auto events = pipeline.beforeStep(sim);
  ASSERT_EQ(events.size(), 2u);
  EXPECT_EQ(events[0].kind, CommandPipeline::Event::Kind::Taken);
  EXPECT_EQ(events[1].kind, CommandPipeline::Event::Kind::Limited);
  EXPECT_EQ(events[1].rule, GuardRule::LinearSpeed);
  EXPECT_NEAR((traj.pose(0.1).position - rest.position).norm(), 0.005, 1e-3);
  EXPECT_GT((traj.pose(0.15).position - c.position).norm(), 1e-3);
  EXPECT_NEAR((traj.pose(0.25).position - c.position).norm(), 0.0, 1e-9);
  // Another source while robot_a owns the needle: refused.
  PoseCommand other = c;
  other.source = "robot_b";
  other.stamp = 0.01;
  const Admission b = pipeline.submit(0, other, 0.01);
  EXPECT_FALSE(b.accepted);
  EXPECT_EQ(b.rule, GuardRule::Owner);
  // A plan at 0.5 m/s from robot_a: refused whole, its sender told why.
  std::string told = "<not called>";
  CommandPipeline::Plan fast{0, {{0.02, rest.position + 0.01 * rest.direction, orientationOf(rest, rest), 0, 0}},
                             "test plan", [&](const std::string& why) { told = why; }, "robot_a"};
  pipeline.submitPlan(fast);
  events = pipeline.beforeStep(sim);
  ASSERT_EQ(events.size(), 1u);
  EXPECT_EQ(events[0].kind, CommandPipeline::Event::Kind::Refused);
  EXPECT_EQ(events[0].rule, GuardRule::Plan);
  EXPECT_NE(told.find("linear_speed"), std::string::npos) << told;
  // A hold: the needle stops where it is commanded to be now.
  sim.step();
  pipeline.hold(0);
  pipeline.beforeStep(sim);
  const Vec3 held = traj.pose(sim.time()).position;
  EXPECT_NEAR((traj.pose(sim.time() + 1.0).position - held).norm(), 0.0, 1e-12);
  EXPECT_TRUE(CommandPipeline::inserted(sim, 0) == false);  // still outside the phantom
  // Limits lowered under a motion: it slows down.
  PoseCommand far = c;
  far.position = rest.position + 0.004 * rest.direction;
  far.stamp = sim.time();  // 4 mm on at the limit: 0.08 s under way
  ASSERT_TRUE(pipeline.submit(0, far, sim.time()).accepted);
  pipeline.beforeStep(sim);
  const double end_before = traj.lastTime();
  CommandLimits slow = limits;
  slow.max_speed = 0.005;
  pipeline.guard().setLimits(slow);
  events = pipeline.beforeStep(sim);
  ASSERT_FALSE(events.empty());
  EXPECT_EQ(events[0].kind, CommandPipeline::Event::Kind::Enforced);
  EXPECT_GT(traj.lastTime(), end_before + 0.2);
}

// Lagged rotations (solver.linear.rotation_drift): a soft, nearly incompressible cantilever
// (the brain's 0.4977) sagging under gravity through tenths of a radian and coming to rest.
// With the factor's rotations in the model every solve is the factor's own matrix: one CG
// iteration a step, where the rotations of every step cost up to the refresh threshold. At
// rest the sag is the exact rotations' to 0.2 % (during the fall the rotations lag by the
// refresh's swap lag as well, and the sag by 2 %: doc/method.md "Time integration").
TEST(LaggedRotations, EverySolveIsTheFactorsMatrixAndTheSagAtRestTheExactRotations) {
  auto run = [](double drift, int& max_iterations, int& swaps) {
    Simulation sim(loadScene(kScenes + "phantom_8x4x4.yaml",
                             {"tissue.material.young=3000", "tissue.material.poisson=0.4977", "time.duration=1.0",
                              "solver.linear.rotation_drift=" + std::to_string(drift)}));
    max_iterations = swaps = 0;
    for (int k = 0; k < 1000; ++k) {
      const StepStats& st = sim.step();
      if (k > 0) max_iterations = std::max(max_iterations, st.linear_iterations);
      swaps += st.async_factorizations;
    }
    return VecX(sim.tissue().positions() - sim.tissue().mesh().restPositions());
  };
  int exact_iterations = 0, exact_swaps = 0, lagged_iterations = 0, lagged_swaps = 0;
  const VecX exact = run(0.0, exact_iterations, exact_swaps);
  const VecX lagged = run(0.01, lagged_iterations, lagged_swaps);
  EXPECT_GT(exact.lpNorm<Eigen::Infinity>(), 0.02);  // the free end sags by centimetres
  EXPECT_GT(exact_iterations, 3);                    // the stale factor costs there
  EXPECT_LE(lagged_iterations, 1);
  EXPECT_GE(lagged_swaps, 3);  // the rotations drifted past 0.01 rad again and again
  EXPECT_LT((lagged - exact).lpNorm<Eigen::Infinity>(), 5e-3 * exact.lpNorm<Eigen::Infinity>());
}

// The compliance columns ahead of the needles (solver.linear.columns_ahead, the live loop's):
// a background factor refresh also computes the columns of the elements the next shaft point
// and the advancing tip will lie in, so that the step meeting them does not solve for them
// (on the DBS mesh 24 columns, 6-12 ms at a 10 ms dt). dbs_coarse with the node's lagged
// rotations, against the same insertion without: the steps solve for at most half the columns
// (measured: 24 of 48, the tip's new element once off the sampled points; the shaft points'
// none), and the motion is the same to round-off (the columns are the same factor's, computed
// elsewhere: 1e-13 of the largest displacement).
TEST(ColumnsAhead, TheRefreshesSolveForTheNextConstraintPointsBeforeTheStepsMeetThem) {
  auto run = [](bool ahead, long& solved, long& points, double& umax) {
    Simulation sim(loadScene(kScenes + "dbs_coarse.yaml",
                             {"time.duration=6.0", "solver.linear.rotation_drift=0.01",
                              std::string("solver.linear.columns_ahead=") + (ahead ? "true" : "false")}));
    long before = -1;
    points = 0;
    umax = 0;
    for (long k = 0; k < sim.scene().numSteps(); ++k) {
      sim.step();
      const auto& c = sim.interaction()->constraints();
      // From the first shaft point on (the touch's and the puncture's columns have nothing ahead).
      if (before < 0 && c.size() >= 2) before = sim.tissue().complianceColumnsSolved();
      points = std::max(points, static_cast<long>(c.size()));
      umax = std::max(umax, (sim.tissue().positions() - sim.tissue().mesh().restPositions()).lpNorm<Eigen::Infinity>());
    }
    solved = sim.tissue().complianceColumnsSolved() - std::max(before, 0L);
    return VecX(sim.tissue().positions());
  };
  long solved_off = 0, solved_on = 0, points = 0;
  double umax = 0;
  const VecX off = run(false, solved_off, points, umax);
  const VecX on = run(true, solved_on, points, umax);
  std::printf("columns solved by the steps after the first shaft point: %ld without, %ld with the columns ahead "
              "(%ld constraint points at most); positions differ by %.3g of the largest displacement\n",
              solved_off, solved_on, points, (on - off).lpNorm<Eigen::Infinity>() / umax);
  ASSERT_GE(points, 4);
  ASSERT_GE(solved_off, 24) << "the insertion must need columns of new elements";
  EXPECT_LE(solved_on, solved_off / 2);
  EXPECT_LT((on - off).lpNorm<Eigen::Infinity>(), 1e-6 * umax);
}

// The adaptivity driver (paper §2.3, doc/method.md, doc/verification.md): refining mid-simulation moves no
// material (probes exact, momentum exact, kinetic energy to interpolation accuracy),
// refine-then-coarsen returns the original mesh and field, coarsening waits for its
// hysteresis, the DOF budget holds, the boundary of a refined mesh is the domain's boundary,
// constraint points are re-embedded exactly, and the adaptive phantom approaches the fine
// uniform one with fewer DOFs.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <map>
#include <sstream>
#include <string>

#include "needle_sim/adapt/mesh_adaptation.hpp"
#include "needle_sim/core/blas_threads.hpp"
#include "needle_sim/fem/embedded_point.hpp"
#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/sim/simulation.hpp"

using namespace needle_sim;

namespace {
const std::string kScenes = std::string(NEEDLE_SIM_SOURCE_DIR) + "/config/scenes/";

Vec3 momentum(const TissueBody& t) {
  Vec3 p = Vec3::Zero();
  for (int i = 0; i < t.mesh().numNodes(); ++i)
    p += t.lumpedMass()[3 * i] * t.velocities().segment<3>(3 * i);
  return p;
}

std::vector<Vec3> probes(const Simulation& s) {
  std::vector<Vec3> u;
  for (int i = 0; i < s.numProbes(); ++i) u.push_back(s.probeDisplacement(i));
  return u;
}

double maxNorm(const std::vector<Vec3>& u) {
  double m = 0;
  for (const auto& v : u) m = std::max(m, v.norm());
  return m;
}

// Elements whose centroid lies within r of point c.
std::vector<int> elementsNear(const HexMesh& m, const Vec3& c, double r) {
  std::vector<int> out;
  for (int e = 0; e < m.numElements(); ++e)
    if ((m.elementCorners(e).colwise().mean().transpose() - c).norm() < r) out.push_back(e);
  return out;
}

// Dynamic phantom under a strong, sudden gravity: a smooth, moving field.
Scene swingingPhantom() {
  return loadScene(kScenes + "phantom_8x4x4.yaml",
                   {"tissue.gravity=[0, 0, -2000]", "adaptivity={theta: 0.3, max_level: 2, every_steps: 1000000}"});
}

// A synthetic estimate of the active mesh of `ad`: eta from each element's centroid.
template <class F>
ErrorEstimate syntheticEstimate(const MeshAdaptation& ad, F eta_of) {
  ErrorEstimate est;
  const auto& act = ad.active();
  double s = 0;
  for (int e = 0; e < act.mesh.numElements(); ++e) {
    const double v = eta_of(Vec3(act.mesh.elementCorners(e).colwise().mean().transpose()));
    est.eta.push_back(v);
    est.max = std::max(est.max, v);
    s += v * v;
  }
  est.global = std::sqrt(s);
  est.energy = 10 * est.global;
  return est;
}
}  // namespace

TEST(RefinedBoundary, FacesCoverTheBoxSurfaceOnce) {
  AdaptivitySettings a;
  a.max_level = 3;
  MeshAdaptation ad(a, HexMesh::box(Vec3(0, 0, 0), Vec3(2, 1, 1), Vec3i(2, 1, 1)));
  ad.refineElements({0});
  ad.refineElements(elementsNear(ad.active().mesh, Vec3(0.25, 0.25, 0.25), 0.1));
  ASSERT_GT(ad.active().numHanging(), 0);
  const HexMesh& m = ad.active().mesh;
  double area = 0;
  for (const auto& f : m.boundaryFaces()) {
    const Vec3 a0 = m.node(f.nodes[0]), a1 = m.node(f.nodes[1]), a2 = m.node(f.nodes[2]), a3 = m.node(f.nodes[3]);
    area += 0.5 * (a2 - a0).cross(a3 - a1).norm();
    const Vec3 c = 0.25 * (a0 + a1 + a2 + a3);
    const bool on_boundary = std::abs(c.x()) < 1e-12 || std::abs(c.x() - 2) < 1e-12 || std::abs(c.y()) < 1e-12 ||
                             std::abs(c.y() - 1) < 1e-12 || std::abs(c.z()) < 1e-12 || std::abs(c.z() - 1) < 1e-12;
    EXPECT_TRUE(on_boundary) << "interior face reported as boundary at " << c.transpose();
  }
  EXPECT_NEAR(area, 10.0, 1e-12);  // 2 (2x1) + 2 (2x1) + 2 (1x1)
}

TEST(Adaptivity, RefiningMidSimulationMovesNoMaterial) {
  Simulation sim(swingingPhantom());
  for (int k = 0; k < 15; ++k) sim.step();
  const auto u0 = probes(sim);
  const Vec3 p0 = momentum(sim.tissue());
  const double ke0 = sim.tissue().kineticEnergy();
  const int dofs0 = sim.tissue().mesh().numDofs();
  ASSERT_GT(ke0, 0);
  // Refine around the probes (on the axis and the radial line), then once more at the tip.
  auto r = sim.refineElements(elementsNear(sim.tissue().mesh(), Vec3(0.005, 0.01, 0.012), 0.008));
  ASSERT_TRUE(r.changed);
  r = sim.refineElements(elementsNear(sim.tissue().mesh(), Vec3(0.003, 0.01, 0.011), 0.003));
  ASSERT_TRUE(r.changed);
  EXPECT_GT(sim.tissue().mesh().numDofs(), dofs0);
  EXPECT_GT(sim.adaptation()->active().numHanging(), 0);
  const auto u1 = probes(sim);
  for (size_t i = 0; i < u0.size(); ++i)
    EXPECT_LT((u1[i] - u0[i]).norm(), 1e-12 * maxNorm(u0)) << sim.probeName(static_cast<int>(i));
  // Lumped mass: momentum = int rho v_h, and v_h is unchanged (nested spaces).
  EXPECT_LT((momentum(sim.tissue()) - p0).norm(), 1e-12 * p0.norm());
  // Kinetic energy of the lumped mass changes by the lumping error of the refined
  // elements only (O(h^2)): measured 0.3 %.
  const double ke1 = sim.tissue().kineticEnergy();
  std::printf("kinetic energy %.6e -> %.6e (%.3f %%), dofs %d -> %d\n", ke0, ke1, 100 * (ke1 - ke0) / ke0, dofs0,
              sim.tissue().mesh().numDofs());
  EXPECT_LT(std::abs(ke1 - ke0), 0.02 * ke0) << ke0 << " -> " << ke1;
  // And the simulation goes on, close to the unrefined one.
  Simulation ref(swingingPhantom());
  for (int k = 0; k < 25; ++k) ref.step();
  for (int k = 0; k < 10; ++k) sim.step();
  const auto ua = probes(sim), ub = probes(ref);
  for (size_t i = 0; i < ua.size(); ++i) EXPECT_LT((ua[i] - ub[i]).norm(), 0.05 * maxNorm(ub));
}

TEST(Adaptivity, RefineThenCoarsenRestoresMeshAndField) {
  Simulation sim(swingingPhantom());
  for (int k = 0; k < 10; ++k) sim.step();
  const HexMesh m0 = sim.tissue().mesh();
  const VecX x0 = sim.tissue().positions(), v0 = sim.tissue().velocities();
  sim.refineElements(elementsNear(m0, Vec3(0.01, 0.01, 0.01), 0.009));
  sim.refineElements(elementsNear(sim.tissue().mesh(), Vec3(0.01, 0.01, 0.01), 0.004));
  ASSERT_GT(sim.tissue().mesh().numElements(), m0.numElements());
  for (int pass = 0; pass < 4; ++pass) {
    std::vector<int> all(sim.tissue().mesh().numElements());
    for (size_t e = 0; e < all.size(); ++e) all[e] = static_cast<int>(e);
    sim.coarsenElements(all);
  }
  const HexMesh& m1 = sim.tissue().mesh();
  ASSERT_EQ(m1.numNodes(), m0.numNodes());
  ASSERT_EQ(m1.numElements(), m0.numElements());
  for (int e = 0; e < m0.numElements(); ++e) EXPECT_EQ(m1.element(e), m0.element(e));
  for (int i = 0; i < m0.numNodes(); ++i) EXPECT_EQ(m1.node(i), m0.node(i));
  EXPECT_EQ((sim.tissue().positions() - x0).lpNorm<Eigen::Infinity>(), 0.0);
  EXPECT_EQ((sim.tissue().velocities() - v0).lpNorm<Eigen::Infinity>(), 0.0);
}

TEST(Adaptivity, CoarseningWaitsForItsHysteresis) {
  AdaptivitySettings a;
  a.theta = 0.5;
  a.max_level = 1;
  a.coarsen = true;
  a.theta_coarsen = 0.1;
  a.coarsen_after = 3;
  MeshAdaptation ad(a, HexMesh::box(Vec3(0, 0, 0), Vec3(4, 4, 4), Vec3i(4, 4, 4)));
  auto estimate = [&](auto eta_of) { return syntheticEstimate(ad, [&](const Vec3& c) { return eta_of(c, 0); }); };
  // A large error in the corner element: it alone is refined.
  auto r = ad.adapt(estimate([](const Vec3& c, int) { return c.norm() < 1 ? 1.0 : 0.01; }));
  EXPECT_EQ(r.refined, 1);
  EXPECT_EQ(ad.active().mesh.numElements(), 64 - 1 + 8);
  // The error moves to the far corner (already at max level after one more pass there);
  // the children are now small but are merged only at the third consecutive pass.
  auto moved = [](const Vec3& c, int) { return (c - Vec3(3.5, 3.5, 3.5)).norm() < 0.5 ? 1.0 : 0.001; };
  r = ad.adapt(estimate(moved));
  EXPECT_EQ(r.coarsened, 0);
  EXPECT_EQ(r.refined, 1);  // the far corner
  r = ad.adapt(estimate(moved));
  EXPECT_EQ(r.coarsened, 0);
  EXPECT_FALSE(r.changed);
  r = ad.adapt(estimate(moved));
  EXPECT_EQ(r.coarsened, 1);
  // A merged element's error (about twice its children's combined, here 2 * sqrt(8) * 0.001)
  // stays below theta * max: it is not refined again.
  r = ad.adapt(estimate(moved));
  EXPECT_FALSE(r.changed);
}

// After keepCurrentRefinement (the brain shift's mesh), small errors there never merge it;
// refinement made afterwards still coarsens as usual.
TEST(Adaptivity, KeptRefinementIsNeverCoarsened) {
  AdaptivitySettings a;
  a.theta = 0.5;
  a.max_level = 1;
  a.coarsen = true;
  a.theta_coarsen = 0.1;
  a.coarsen_after = 1;
  MeshAdaptation ad(a, HexMesh::box(Vec3(0, 0, 0), Vec3(4, 4, 4), Vec3i(4, 4, 4)));
  auto estimate = [&](auto eta_of) { return syntheticEstimate(ad, eta_of); };
  ASSERT_EQ(ad.adapt(estimate([](const Vec3& c) { return c.norm() < 1 ? 1.0 : 0.01; })).refined, 1);
  ad.keepCurrentRefinement();
  auto far = [](const Vec3& c) { return (c - Vec3(3.5, 3.5, 3.5)).norm() < 0.5 ? 1.0 : 0.001; };
  auto r = ad.adapt(estimate(far));
  EXPECT_EQ(r.coarsened, 0);  // the kept corner stays refined
  EXPECT_EQ(r.refined, 1);    // the far corner is refined
  auto near = [](const Vec3& c) { return c.norm() < 1 ? 1.0 : 0.001; };
  r = ad.adapt(estimate(near));
  EXPECT_EQ(r.coarsened, 1);  // the far corner merges back
  EXPECT_EQ(ad.active().mesh.numElements(), 64 - 1 + 8);
  for (int k = 0; k < 3; ++k) EXPECT_FALSE(ad.adapt(estimate(far)).coarsened);
}

TEST(Adaptivity, DofBudgetHolds) {
  AdaptivitySettings a;
  a.theta = 0.01;  // marks nearly everything
  a.max_level = 2;
  a.max_dofs = 1500;
  MeshAdaptation ad(a, HexMesh::box(Vec3(0, 0, 0), Vec3(4, 2, 2), Vec3i(8, 4, 4)));
  ErrorEstimate est;
  for (int e = 0; e < ad.active().mesh.numElements(); ++e) est.eta.push_back(1.0 + 0.01 * e);
  est.max = est.eta.back();
  est.global = 10;
  est.energy = 100;
  const auto r = ad.adapt(est);
  EXPECT_TRUE(r.budget_reached);
  EXPECT_GT(r.refined, 0);
  EXPECT_LE(ad.numDofs(), 1500);
  EXPECT_GT(ad.numDofs(), 1500 - 3 * 19 * 4);  // stops within a few cells of the budget
}

TEST(Adaptivity, StaticPhantomApproachesTheFineUniformMesh) {
  // Gravity sag of the clamped phantom: solve, estimate, mark (theta 0.3), refine, 4 times.
  const std::string f = kScenes + "phantom_8x4x4.yaml";
  Simulation coarse(loadScene(f, {"solver.mode=static", "time.duration=0.001"}));
  coarse.step();
  Simulation fine(loadScene(f, {"solver.mode=static", "time.duration=0.001", "tissue.grid.cells=[16,8,8]"}));
  fine.step();
  Simulation adaptive(loadScene(f, {"solver.mode=static", "time.duration=0.004", "adaptivity={theta: 0.3, max_level: 1}"}));
  for (int k = 0; k < 4; ++k) adaptive.step();
  EXPECT_LT(adaptive.tissue().mesh().numDofs(), fine.tissue().mesh().numDofs());
  EXPECT_GT(adaptive.tissue().mesh().numDofs(), coarse.tissue().mesh().numDofs());
  const auto uc = probes(coarse), uf = probes(fine), ua = probes(adaptive);
  double ec = 0, ea = 0;
  for (size_t i = 0; i < uf.size(); ++i) {
    ec = std::max(ec, (uc[i] - uf[i]).norm());
    ea = std::max(ea, (ua[i] - uf[i]).norm());
  }
  std::printf("probe error vs 16x8x8: coarse %.3e m, adaptive %.3e m (%d DOFs vs %d)\n", ec, ea,
              adaptive.tissue().mesh().numDofs(), fine.tissue().mesh().numDofs());
  // Measured: coarse 6.2e-7 m, adaptive 2.2e-8 m from the 16x8x8 probes (of 1.0e-5 m).
  EXPECT_LT(ea, 0.1 * ec) << "adaptive " << ea << " coarse " << ec;
}

TEST(Adaptivity, InsertionReembedsConstraintPointsExactly) {
  Scene s = loadScene(kScenes + "phantom_insertion_8x4x4.yaml",
                      {"time.duration=1.5", "adaptivity={theta: 0.3, max_level: 2, every_steps: 10}"});
  Simulation sim(s);
  while (sim.interaction()->activePoints(0) < 4) sim.step();
  // Some passes have refined along the path already; refine where the constraints are.
  const auto& cons = sim.interaction()->constraints();
  std::vector<Vec3> before;
  std::vector<int> els;
  for (const auto& c : cons) {
    before.push_back(c->tissue.interpolate(sim.tissue().mesh(), sim.tissue().positions()));
    els.push_back(c->tissue.element);
  }
  const std::vector<int> levels = sim.elementLevels();
  EXPECT_GE(*std::max_element(levels.begin(), levels.end()), 1);
  sim.refineElements(els);
  for (size_t i = 0; i < cons.size(); ++i) {
    const Vec3 after = cons[i]->tissue.interpolate(sim.tissue().mesh(), sim.tissue().positions());
    EXPECT_LT((after - before[i]).norm(), 1e-15) << "constraint " << i;
  }
  // And the insertion goes on: more constraints, finite forces, the mesh follows the path.
  const int n0 = sim.interaction()->activePoints(0);
  for (int k = 0; k < 300; ++k) sim.step();
  EXPECT_GT(sim.interaction()->activePoints(0), n0);
  EXPECT_TRUE(sim.needle(0).baseForce().allFinite());
}

// Deferred mesh changes (adaptivity.rebuild_delay): the new body is built in the background and
// the simulation moves to it exactly the delay's steps after the pass that decided it (the state is
// carried by the same transfer as a synchronous change, whose tests above keep their
// tolerances; the accuracy against 32x16x16 is the next test's, on the shipped scene's lag);
// the results do not depend on when the build finishes (a late build only makes the switch
// wait); a copy taken while a build is pending steps exactly as the original.
// With either ordering: METIS orders with a random generator in globals, and orderings made
// on two threads at once (a build and a copy's build) differed before analyses were
// serialised (CholmodSolver::analyze); AMD has no such state.
TEST(Adaptivity, DeferredMeshChangesSwitchAtTheirStepAndCarryTheState) {
 for (const std::string ordering : {"auto", "metis"}) {
  SCOPED_TRACE("ordering " + ordering);
  // (The pass itself on this thread: BackgroundPassesDecideAsPassesOnTheSteppingThread.)
  const std::vector<std::string> sets = {"time.duration=0.8", "adaptivity.rebuild_delay=0.007",
                                         "adaptivity.estimate_delay=0", "solver.linear.ordering=" + ordering};
  struct Trace {
    std::vector<VecX> x;
    long deferred = 0, waits = 0;
  };
  auto run = [&](double delay_ms, bool checks) {
    Simulation::setRebuildDelayForTesting(delay_ms);
    Simulation sim(loadScene(kScenes + "phantom_insertion_adaptive.yaml", sets));
    Trace tr;
    long decided = -1, switches = 0;
    std::unique_ptr<Simulation> copy;
    for (long k = 0; k < sim.scene().numSteps(); ++k) {
      const bool was_pending = sim.rebuildPending();
      const int dofs = sim.tissue().mesh().numDofs();
      sim.step();
      if (copy) copy->step();
      if (!was_pending && sim.rebuildPending()) decided = sim.stepIndex();
      if (checks && was_pending && !sim.rebuildPending()) {
        ++switches;
        EXPECT_EQ(sim.stepIndex(), decided + 7) << "the switch comes rebuild_delay (7 steps of 1 ms) after the decision";
        EXPECT_NE(sim.tissue().mesh().numDofs(), dofs);
        EXPECT_EQ(sim.lastStats().mesh_changed, true);
      }
      if (checks && sim.rebuildPending() && !copy) copy = std::make_unique<Simulation>(sim);
      tr.x.push_back(sim.tissue().positions());
    }
    if (checks) {
      EXPECT_GT(switches, 1);
      EXPECT_TRUE(copy != nullptr);
      if (copy) {
        EXPECT_EQ(copy->tissue().mesh().numDofs(), sim.tissue().mesh().numDofs());
        EXPECT_EQ((copy->tissue().positions() - sim.tissue().positions()).lpNorm<Eigen::Infinity>(), 0.0);
      }
    }
    tr.deferred = sim.adaptationCounters().deferred_rebuilds;
    tr.waits = sim.adaptationCounters().rebuild_waits;
    Simulation::setRebuildDelayForTesting(0);
    return tr;
  };
  const Trace on_time = run(0, true), late = run(15, false);
  ASSERT_GT(on_time.deferred, 1);
  EXPECT_EQ(late.deferred, on_time.deferred);
  EXPECT_GT(late.waits, 0);
  ASSERT_EQ(late.x.size(), on_time.x.size());
  for (size_t k = 0; k < late.x.size(); ++k)
    ASSERT_EQ((late.x[k] - on_time.x[k]).lpNorm<Eigen::Infinity>(), 0.0) << "step " << k + 1;
 }
}

// Background passes (adaptivity.estimate_delay): the estimate, the marking and the new forest
// are made on another thread from a copy of the pass's state, the decision taken up
// estimate_delay later, a change switched to at the step a pass on the stepping thread would
// have switched at. A pass due before that at a touch or puncture takes the decision up at
// once (waiting for it); one due at a new shaft point starts after it, at its step (since
// 2026-12-04: waiting made the slowest steps). The run is the same bit for bit however late
// the background thread is; a copy taken while a pass is under way steps as the original;
// and the run is close to that of passes on the stepping thread (here, over the first
// 1.25 s with three such passes, the same; deferring the puncture's pass too moved the
// probes by 3.4 % of their largest displacement, which the 1 % check below catches). On the
// paper's element, where that was measured: on the default one the decisions taken up 5 steps
// later part from the stepping thread's at step 810 (a shaft point's pass) and the probes by
// 1.6 %, so that the check would not tell the deferred puncture from the designed deferral.
TEST(Adaptivity, BackgroundPassesDecideAsPassesOnTheSteppingThread) {
  struct Trace {
    std::vector<VecX> x;
    std::vector<std::vector<Vec3>> probes;
    long passes = 0, waits = 0, changes = 0, after_decision = 0;
  };
  auto run = [&](const std::string& estimate_delay, double late_ms, bool checks) {
    Simulation::setRebuildDelayForTesting(late_ms);
    Simulation sim(loadScene(kScenes + "phantom_insertion_adaptive.yaml",
                             {"time.duration=1.25", "adaptivity.rebuild_delay=0.007",
                              "adaptivity.estimate_delay=" + estimate_delay, "tissue.element=trilinear"}));
    Trace tr;
    std::unique_ptr<Simulation> copy;
    long started = -1;
    for (long k = 0; k < sim.scene().numSteps(); ++k) {
      const long passes = sim.adaptationCounters().background_passes;
      sim.step();
      if (copy) copy->step();
      if (sim.adaptationCounters().background_passes > passes) started = sim.stepIndex();
      if (checks && sim.passPending()) {
        EXPECT_LT(sim.stepIndex(), started + 5) << "a decision is taken up 5 steps (5 ms) after its pass at the latest";
        if (!copy && sim.stepIndex() > 300) copy = std::make_unique<Simulation>(sim);
      }
      tr.x.push_back(sim.tissue().positions());
      tr.probes.emplace_back();
      for (int i = 0; i < sim.numProbes(); ++i) tr.probes.back().push_back(sim.probeDisplacement(i));
    }
    if (checks) {
      EXPECT_TRUE(copy != nullptr);
      if (copy) {
        EXPECT_EQ(copy->tissue().mesh().numDofs(), sim.tissue().mesh().numDofs());
        EXPECT_EQ((copy->tissue().positions() - sim.tissue().positions()).lpNorm<Eigen::Infinity>(), 0.0);
      }
    }
    tr.passes = sim.adaptationCounters().background_passes;
    tr.waits = sim.adaptationCounters().pass_waits;
    tr.changes = sim.adaptationCounters().deferred_rebuilds;
    tr.after_decision = sim.adaptationCounters().passes_after_decision;
    Simulation::setRebuildDelayForTesting(0);
    return tr;
  };
  const Trace here = run("0", 0, false), background = run("0.005", 0, true), late = run("0.005", 15, false);
  EXPECT_EQ(here.passes, 0);
  EXPECT_GT(background.passes, 20);
  ASSERT_GT(here.changes, 1);
  EXPECT_GT(background.changes, 1);
  EXPECT_EQ(late.changes, background.changes);
  EXPECT_GT(late.waits, 0) << "15 ms late passes must have been waited for";
  // New shaft points within estimate_delay of a regular pass: those passes started after its
  // decision, at the same steps however late the thread was.
  EXPECT_EQ(here.after_decision, 0);
  EXPECT_GT(background.after_decision, 0);
  EXPECT_EQ(late.after_decision, background.after_decision);
  ASSERT_EQ(late.x.size(), background.x.size());
  for (size_t k = 0; k < background.x.size(); ++k) {
    ASSERT_EQ(late.x[k].size(), background.x[k].size()) << "step " << k + 1;
    ASSERT_EQ((late.x[k] - background.x[k]).lpNorm<Eigen::Infinity>(), 0.0) << "step " << k + 1;
  }
  // Close to the passes on the stepping thread: the probes' displacements at every step,
  // relative to the largest.
  double d = 0, umax = 0;
  long worst = -1;
  for (size_t k = 0; k < here.probes.size(); ++k)
    for (size_t i = 0; i < here.probes[k].size(); ++i) {
      umax = std::max(umax, here.probes[k][i].norm());
      const double dk = (background.probes[k][i] - here.probes[k][i]).norm();
      if (dk > d) { d = dk; worst = static_cast<long>(k) + 1; }
    }
  std::printf("background against stepping-thread passes: probes differ by %.3g of the largest displacement at most (step %ld)\n", d / umax, worst);
  EXPECT_LT(d, 0.01 * umax);
}

// The adaptive phantom insertion (theta 0.3, 2 levels over 8x4x4; the shipped scene refines
// 0.4 s ahead of the tip, the first run below does not) against the uniform
// 32x16x16 run, whose probe displacements (every 10th step) are kept in test/data/reference
// (the file says how it was produced), and against the uniform 16x8x8 run with more DOFs
// than it ever has. Outside the contact instant (the puncture is a one-step transient
// computed on the mesh of the step before, as adaptation follows the event), on the stored
// steps, as a share of the largest stored probe displacement. Measured on the default
// element (2026-12-05): adaptive max 0.19, time-mean 0.010, at most 1,509 tissue DOFs against
// 28,611; uniform 16x8x8 0.42 and 0.073 with 4,131 DOFs (8x4x4: 0.72 and 0.14). The adaptive
// run's largest differences are transients where a region coarsened earlier is re-refined
// late as the tip comes near a probe (p4 at steps 1,180-1,230: 0.01 -> 0.23, back to 0.01 at
// the refinement); with the paper's element the same schedule gave 0.066 and 0.0075, on a
// reference 8 % stiffer. Refined ahead (shipped): 0.016 outside the puncture and 0.039 at it
// (0.60 without), 1,878 DOFs.
TEST(Adaptivity, PhantomInsertionAgreesWithUniform32x16x16) {
#ifdef NEEDLE_SIM_SANITIZED
  GTEST_SKIP() << "a whole adaptive insertion (2 min under ASan): InsertionReembedsConstraintPointsExactly runs the "
                  "same mesh changes under the sanitizers";
#endif
  std::ifstream in(std::string(NEEDLE_SIM_SOURCE_DIR) + "/test/data/reference/phantom_insertion_32x16x16_probes.csv");
  ASSERT_TRUE(in) << "reference file missing";
  std::string line;
  std::vector<std::string> header;
  std::vector<std::vector<std::string>> rows;
  auto split = [](const std::string& s) {
    std::vector<std::string> out;
    std::stringstream ss(s);
    for (std::string f; std::getline(ss, f, ',');) out.push_back(f);
    return out;
  };
  while (std::getline(in, line)) {
    if (line.empty() || line[0] == '#') continue;
    if (header.empty()) header = split(line);
    else rows.push_back(split(line));
  }
  ASSERT_EQ(rows.size(), 500u);
  setBlasThreads(1);  // as the tool: the same summation order, so the same run as the README's
  std::map<std::string, int> col;
  for (size_t i = 0; i < header.size(); ++i) col[header[i]] = static_cast<int>(i);
  long first_contact = -1;
  for (const auto& r : rows)
    if (first_contact < 0 && r[1] != "approaching") first_contact = std::stol(r[0]);
  struct Agreement {
    double max = 0, mean = 0, with_puncture = 0;  // with_puncture: the largest at any compared step
    int max_dofs = 0;
  };
  double umax = 0;
  auto against = [&](const std::string& scene, const std::vector<std::string>& overrides = {}) {
    Simulation sim(loadScene(kScenes + scene, overrides));
    Agreement a;
    double esum = 0;
    size_t next = 0;
    while (next < rows.size()) {
      sim.step();
      a.max_dofs = std::max(a.max_dofs, sim.tissue().mesh().numDofs());
      const auto& r = rows[next];
      if (sim.stepIndex() != std::stol(r[0])) continue;
      ++next;
      double e = 0;
      for (int i = 0; i < sim.numProbes(); ++i) {
        const std::string& n = sim.probeName(i);
        const Vec3 ref(std::stod(r[col.at(n + "_ux")]), std::stod(r[col.at(n + "_uy")]), std::stod(r[col.at(n + "_uz")]));
        umax = std::max(umax, ref.norm());
        e = std::max(e, (sim.probeDisplacement(i) - ref).norm());
      }
      a.with_puncture = std::max(a.with_puncture, e);
      if (std::abs(sim.stepIndex() - first_contact) <= 10) continue;
      a.max = std::max(a.max, e);
      esum += e;
    }
    a.mean = esum / rows.size();
    return a;
  };
  // The shipped scene without its refinement ahead of the tip: the estimate alone.
  const Agreement adaptive = against("phantom_insertion_adaptive.yaml", {"adaptivity.lookahead=0"});
  const Agreement uniform = against("phantom_insertion_16x8x8.yaml");
  // The shipped scene: refined ahead of the tip over the trajectory's next 0.4 s (#38 item 3),
  // the mesh no longer lags the tip, nor the entry point the touch.
  const Agreement ahead = against("phantom_insertion_adaptive.yaml");
  ASSERT_GT(umax, 0);
  std::printf("against 32x16x16: adaptive max %.4f, time-mean %.4f of the largest probe displacement, max %d tissue DOFs; "
              "uniform 16x8x8 %.4f, %.4f, %d DOFs\n",
              adaptive.max / umax, adaptive.mean / umax, adaptive.max_dofs, uniform.max / umax, uniform.mean / umax,
              uniform.max_dofs);
  // Closer than the uniform mesh with more DOFs, by half at its worst and five times on average.
  EXPECT_LT(adaptive.max_dofs, uniform.max_dofs / 2);
  EXPECT_LT(adaptive.max, 0.5 * uniform.max);
  EXPECT_LT(adaptive.mean, 0.2 * uniform.mean);
  EXPECT_LT(adaptive.mean / umax, 0.02);
  EXPECT_LT(adaptive.max_dofs, 28611 / 10);
  std::printf("shipped, with lookahead 0.4 s: max %.4f, at any compared step %.4f (without: %.4f), %d DOFs\n", ahead.max / umax,
              ahead.with_puncture / umax, adaptive.with_puncture / umax, ahead.max_dofs);
  EXPECT_LT(ahead.max / umax, 0.02);            // the goal (#38): 2 %
  EXPECT_LT(ahead.with_puncture / umax, 0.10);  // every compared step, the touch's 10 included, within 10 %
  EXPECT_GT(adaptive.with_puncture / umax, 0.10);  // which it is not without (the comparison says something)
  EXPECT_LT(ahead.max_dofs, 28611 / 10);
}

// Refinement ahead of the tip (adaptivity.lookahead, #38 item 3): the passes refine the path
// the trajectory says the tip will take, so the element holding the tip's material point is
// at max_level from the touch on, though mesh changes switch 30 ms after their pass and the
// SPR estimate sees an error only once the tip has moved the tissue. Without it the tip
// enters coarse elements (the mesh lags it).
TEST(Adaptivity, LookaheadRefinesThePathBeforeTheTipGetsThere) {
  struct Lag {
    int steps = 0, coarse = 0;     // steps in the tissue, of them with the tip in a coarser element
    int touch_level = -1;          // the entry element's level at the touch
    long ahead = 0;                // elements refined for lying ahead
  };
  auto run = [](const std::string& lookahead) {
    Simulation sim(loadScene(kScenes + "phantom_insertion_adaptive.yaml",
                             {"time.duration=1.6", "adaptivity.lookahead=" + lookahead}));
    const int max_level = sim.scene().adaptivity->max_level;
    Lag lag;
    auto levelAt = [&](const Vec3& p) {  // in the mesh the steps use (not the forest a pass may be changing)
      const PointLocator locator(sim.tissue().mesh());
      EmbeddedPoint ep;
      return locator.locate(p, ep) ? sim.elementLevels()[ep.element] : -1;
    };
    InsertionState before = InsertionState::Approaching;
    for (long k = 0; k < sim.scene().numSteps(); ++k) {
      sim.step();
      const InsertionState s = sim.interaction()->state(0);
      if (before == InsertionState::Approaching && s == InsertionState::InContact)
        lag.touch_level = levelAt(sim.needle(0).tipPosition() + 1e-4 * sim.needle(0).tipDirection());
      before = s;
      if (s != InsertionState::Inserted) continue;
      ++lag.steps;
      if (levelAt(sim.interaction()->cutPath(0).back()) < max_level) ++lag.coarse;
    }
    lag.ahead = sim.adaptationCounters().ahead_marked;
    return lag;
  };
  setBlasThreads(1);  // one summation order: the same run every time
  const Lag with = run("0.1"), without = run("0");
  std::printf("tip in a coarser element: %d of %d steps with lookahead (%ld marked ahead), %d of %d without; "
              "entry element's level at the touch: %d with, %d without\n",
              with.coarse, with.steps, with.ahead, without.coarse, without.steps, with.touch_level, without.touch_level);
  ASSERT_GT(with.steps, 500);
  EXPECT_GT(without.coarse, 0);  // the comparison says something: without it the mesh lags
  EXPECT_EQ(with.coarse, 0);
  EXPECT_EQ(with.touch_level, 2);
  EXPECT_LT(without.touch_level, 2);
  EXPECT_GT(with.ahead, 0);
  EXPECT_EQ(without.ahead, 0);
}

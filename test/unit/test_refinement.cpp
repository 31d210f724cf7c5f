// Template refinement with hanging nodes (doc/method.md, doc/verification.md): volumes preserved, 2:1 balance,
// P a partition of unity, patch test exact with hanging nodes over several levels, SPR of a
// linear field zero, refine-then-coarsen back to the original mesh.
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <random>

#include "fixtures.hpp"
#include "needle_sim/scene/scene.hpp"
#include "needle_sim/adapt/refinable_hex_mesh.hpp"
#include "needle_sim/adapt/spr_estimator.hpp"
#include "needle_sim/tissue/tissue_body.hpp"

using namespace needle_sim;

namespace {

double meshVolume(const HexMesh& m) {
  LinearElasticMaterial mat{1, 0.3, 1};
  CorotationalHexModel model(m, mat);
  double v = 0;
  for (int e = 0; e < m.numElements(); ++e) v += model.reference(e).volume;
  return v;
}

// A box with distorted interior nodes, refined at random over `levels` passes.
RefinableHexMesh randomlyRefined(unsigned seed, int levels, bool distort) {
  HexMesh coarse = HexMesh::box(Vec3(0, 0, 0), Vec3(1, 1, 1), Vec3i(3, 3, 3));
  if (distort) {
    std::mt19937 g(seed);
    std::uniform_real_distribution<double> U(-0.08, 0.08);
    for (int i = 0; i < coarse.numNodes(); ++i) {
      const Vec3 p = coarse.node(i);
      if ((p.array() > 1e-12).all() && (p.array() < 1 - 1e-12).all()) coarse.setNode(i, p + Vec3(U(g), U(g), U(g)));
    }
  }
  RefinableHexMesh rm(coarse);
  std::mt19937 g(seed + 1);
  for (int l = 0; l < levels; ++l) {
    std::vector<int> pick;
    for (int c = 0; c < rm.numCells(); ++c)
      if (rm.isActive(c) && g() % 4 == 0) pick.push_back(c);
    rm.refine(pick);
  }
  return rm;
}

TissueParameters boxScene(HexFormulation element = HexFormulation::Trilinear, double nu = 0.3) {
  TissueParameters t = needle_sim_test::clampedUnitCube(1000.0, nu, 1.0);
  t.material.element = element;
  return t;
}
SolverSettings staticDirect() { return needle_sim_test::staticDirect(1e-13, 100); }

}  // namespace

TEST(Refinement, OneCellInEightWithHangingNodes) {
  RefinableHexMesh rm(HexMesh::box(Vec3(0, 0, 0), Vec3(2, 2, 2), Vec3i(2, 2, 2)));
  EXPECT_EQ(rm.refine({0}), 1);
  const auto a = rm.active();
  EXPECT_EQ(a.mesh.numElements(), 7 + 8);
  EXPECT_EQ(a.mesh.numNodes(), 27 + 19);  // 19 new nodes: 12 edge mids, 6 face centres, 1 body centre
  // Hanging: the centres of the 3 faces shared with unrefined neighbours and the midpoints
  // of the 9 edges shared with a neighbour (only the 3 edges through the box's corner are
  // not).
  EXPECT_EQ(a.numHanging(), 3 + 9);
  EXPECT_NEAR(meshVolume(a.mesh), 8.0, 1e-12);
  for (int e = 0; e < a.mesh.numElements(); ++e) EXPECT_EQ(a.level[e], a.cell[e] >= 8 ? 1 : 0);
}

TEST(Refinement, VolumePreservedOnDistortedMeshes) {
  for (unsigned seed : {1u, 2u, 3u}) {
    RefinableHexMesh rm = randomlyRefined(seed, 3, true);
    HexMesh coarse = HexMesh::box(Vec3(0, 0, 0), Vec3(1, 1, 1), Vec3i(3, 3, 3));
    EXPECT_NEAR(meshVolume(rm.active().mesh), 1.0, 1e-12) << seed;
  }
}

TEST(Refinement, TwoToOneBalanceAndPartitionOfUnity) {
  RefinableHexMesh rm = randomlyRefined(7, 4, false);
  const auto a = rm.active();
  ASSERT_GT(a.numHanging(), 0);
  int max_level = 0;
  for (int l : a.level) max_level = std::max(max_level, l);
  EXPECT_GE(max_level, 3);
  // 2:1: elements sharing a node differ by at most one level... except across a vertex, so
  // check faces and edges through the hanging nodes: a hanging node's masters belong to an
  // element one level coarser than the elements using the hanging node.
  std::vector<int> min_level(a.mesh.numNodes(), 1 << 20), max_l(a.mesh.numNodes(), -1);
  for (int e = 0; e < a.mesh.numElements(); ++e)
    for (int n : a.mesh.element(e)) {
      min_level[n] = std::min(min_level[n], a.level[e]);
      max_l[n] = std::max(max_l[n], a.level[e]);
    }
  for (int n = 0; n < a.mesh.numNodes(); ++n)
    if (!a.hanging[n].empty()) {
      EXPECT_LE(max_l[n] - min_level[n], 1) << "hanging node " << n;
    }
  // P reproduces constants (partition of unity): all DOFs free.
  std::vector<std::vector<std::pair<int, double>>> dof_hanging(3 * a.mesh.numNodes());
  for (int n = 0; n < a.mesh.numNodes(); ++n)
    for (const auto& [m, w] : a.hanging[n])
      for (int d = 0; d < 3; ++d) dof_hanging[3 * n + d].emplace_back(3 * m + d, w);
  DofMap dofs(std::vector<char>(3 * a.mesh.numNodes(), 0), dof_hanging);
  EXPECT_EQ(dofs.numFree(), 3 * (a.mesh.numNodes() - a.numHanging()));
  VecX ones = VecX::Ones(dofs.numFree()), full;
  dofs.scatter(ones, full);
  EXPECT_LT((full - VecX::Ones(full.size())).lpNorm<Eigen::Infinity>(), 1e-14);
  // ... and linear fields: hanging nodes sit at the weighted masters' positions.
  for (int n = 0; n < a.mesh.numNodes(); ++n) {
    if (a.hanging[n].empty()) continue;
    Vec3 p = Vec3::Zero();
    for (const auto& [m, w] : a.hanging[n]) p += w * a.mesh.node(m);
    EXPECT_LT((p - a.mesh.node(n)).norm(), 1e-14);
  }
}

// Patch test with hanging nodes: boundary nodes prescribed to x = F X + c, interior solved
// with P^T A P (CHOLMOD must find it positive definite): every node, hanging ones included,
// on the linear field to 1e-10; the SPR estimate of the result is zero. Every hexahedron
// formulation, the locking-free ones at nu = 0.4999 (#37).
TEST(Refinement, PatchTestWithHangingNodesIsExact) {
  const std::pair<HexFormulation, double> cases[] = {
      {HexFormulation::Trilinear, 0.3},          {HexFormulation::Bbar, 0.3},
      {HexFormulation::IncompatibleModes, 0.3},  {HexFormulation::IncompatibleModesBbar, 0.3},
      {HexFormulation::Bbar, 0.4999},            {HexFormulation::IncompatibleModes, 0.4999},
      {HexFormulation::IncompatibleModesBbar, 0.4999}};
  for (const auto& [element, nu] : cases)
  for (unsigned seed : {11u, 12u}) {
    SCOPED_TRACE("element " + std::to_string(static_cast<int>(element)) + ", nu " + std::to_string(nu));
    RefinableHexMesh rm = randomlyRefined(seed, 3, true);
    const auto a = rm.active();
    ASSERT_GT(a.numHanging(), 0);
    TissueBody body(a.mesh, boxScene(element, nu), staticDirect(), "", a.hanging);
    Mat3 F;
    F << 1.001, 2e-4, -3e-4, 5e-4, 0.998, 1e-4, 0.0, 3e-4, 1.001;  // trace 3: isochoric to first order
    const Vec3 c(1e-3, -2e-3, 5e-4);
    VecX target(a.mesh.numDofs());
    for (int i = 0; i < a.mesh.numNodes(); ++i) target.segment<3>(3 * i) = F * a.mesh.node(i) + c;
    body.setPrescribedPositions(target);
    ASSERT_GT(body.dofs().numFree(), 0);
    body.solveStatic();
    VecX x = body.positions();
    const double err = (x - target).lpNorm<Eigen::Infinity>();
    EXPECT_LT(err, 1e-10 * (target - a.mesh.restPositions()).lpNorm<Eigen::Infinity>()) << "seed " << seed;
    SprEstimator spr(body.model());
    const ErrorEstimate est = spr.estimate(x);
    // Round-off: 1.3e-10 at nu = 0.3 (QR fit); the stresses' round-off grows with lambda / mu
    // (5,000 at nu = 0.4999: 1.2e-8 measured), so the floor is 1e-9 (1 + lambda / mu).
    const LinearElasticMaterial m{1000.0, nu, 1.0};
    EXPECT_LT(est.global, 1e-9 * (1 + m.lameLambda() / m.lameMu()) * est.energy) << "seed " << seed;
  }
}

TEST(Refinement, RefineThenCoarsenReturnsTheOriginalMesh) {
  RefinableHexMesh rm(HexMesh::box(Vec3(0, 0, 0), Vec3(1, 1, 1), Vec3i(3, 3, 3)));
  const auto before = rm.active();
  rm.refine({13});  // the centre cell
  const auto mid = rm.active();
  EXPECT_EQ(mid.mesh.numElements(), 27 - 1 + 8);
  EXPECT_EQ(rm.coarsen({13}), 1);
  const auto after = rm.active();
  ASSERT_EQ(after.mesh.numElements(), before.mesh.numElements());
  EXPECT_EQ(after.numHanging(), 0);
  ASSERT_EQ(after.mesh.numNodes(), before.mesh.numNodes());
  for (int e = 0; e < after.mesh.numElements(); ++e)
    for (int k = 0; k < 8; ++k)
      EXPECT_LT((after.mesh.node(after.mesh.element(e)[k]) - before.mesh.node(before.mesh.element(e)[k])).norm(), 1e-15);
  // Refining again brings back the same cells.
  rm.refine({13});
  EXPECT_EQ(rm.active().mesh.numElements(), mid.mesh.numElements());
  EXPECT_EQ(rm.numCells(), 27 + 8);
}

TEST(Refinement, CoarseningRespectsTheBalance) {
  RefinableHexMesh rm(HexMesh::box(Vec3(0, 0, 0), Vec3(1, 1, 1), Vec3i(3, 3, 3)));
  rm.refine({13});
  const int child = 27;  // first child of the centre cell
  rm.refine({child});    // level 2 inside the centre cell: neighbours must stay refined
  EXPECT_EQ(rm.coarsen({13}), 0);  // its children are not all leaves
}

// MeshAdaptation's DOF budget refines a prefix of the marked cells in one call (a bisection
// on its length when all do not fit): that must give the forest that refining the cells one
// at a time does (the 2:1-balanced closure of the splits is unique).
TEST(Refinement, RefiningAListEqualsRefiningItsCellsOneAtATime) {
  auto cells = [](const RefinableHexMesh& rm) {
    const auto act = rm.active();
    std::vector<std::array<double, 4>> out;  // centre and level of each active cell
    for (int e = 0; e < act.mesh.numElements(); ++e) {
      const Vec3 c = act.mesh.elementCorners(e).colwise().mean();
      out.push_back({std::round(c[0] * 1e9), std::round(c[1] * 1e9), std::round(c[2] * 1e9), double(act.level[e])});
    }
    std::sort(out.begin(), out.end());
    return out;
  };
  for (unsigned seed = 1; seed <= 6; ++seed) {
    const RefinableHexMesh start = randomlyRefined(seed, 2, false);
    // The finest active cells, a few of them at random: their splits cascade through the balance.
    int finest = 0;
    const auto act = start.active();
    for (int e = 0; e < act.mesh.numElements(); ++e) finest = std::max(finest, act.level[e]);
    std::vector<int> pick;
    std::mt19937 g(seed);
    for (int e = 0; e < act.mesh.numElements(); ++e)
      if (act.level[e] == finest && g() % 3 == 0) pick.push_back(act.cell[e]);
    ASSERT_GE(pick.size(), 2u);
    RefinableHexMesh batch = start, one = start;
    const int n_batch = batch.refine(pick);
    int n_one = 0;
    for (int c : pick)
      if (one.isActive(c)) n_one += one.refine({c});
    EXPECT_EQ(n_batch, n_one) << "seed " << seed;
    EXPECT_GT(n_batch, static_cast<int>(pick.size())) << "seed " << seed << ": the balance refined nothing more";
    EXPECT_EQ(cells(batch), cells(one)) << "seed " << seed;
    EXPECT_EQ(batch.numActiveNodes(), one.numActiveNodes());
  }
}

#include "needle_sim/adapt/marking.hpp"

TEST(Marking, MaxRuleAndBulkRule) {
  const std::vector<double> eta = {1.0, 0.2, 0.6, 0.05, 0.9, 0.3};
  std::vector<char> ok(eta.size(), 1);
  // Max rule: eta >= 0.5 * 1.0
  EXPECT_EQ(MaxMarking(0.5).mark(eta, ok), (std::vector<int>{0, 2, 4}));
  // Excluded elements (at max level) are not marked but still set the maximum.
  ok[0] = 0;
  EXPECT_EQ(MaxMarking(0.5).mark(eta, ok), (std::vector<int>{2, 4}));
  EXPECT_EQ(MaxMarking(0.65).mark(eta, ok), (std::vector<int>{4}));  // 0.65 * 1.0, not 0.65 * 0.9
  ok[0] = 1;
  // Bulk: total 2.3025; 60 % = 1.3815; 1.0 + 0.81 = 1.81 >= 1.3815 after two elements.
  EXPECT_EQ(BulkMarking(0.6).mark(eta, ok), (std::vector<int>{0, 4}));
  EXPECT_EQ(BulkMarking(0.9).mark(eta, ok), (std::vector<int>{0, 4, 2}));
  EXPECT_TRUE(MaxMarking(0.5).mark(std::vector<double>(3, 0.0), std::vector<char>(3, 1)).empty());
}

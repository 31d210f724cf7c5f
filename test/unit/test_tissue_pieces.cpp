// The tissue body's pieces on their own: loads and boundary conditions (tissue_loads.hpp),
// the compliance columns (compliance_cache.hpp), the static Newton (static_newton.cpp), and
// the skull contact of the brain shift (skull_contact.hpp).
#include <gtest/gtest.h>

#include <cmath>

#include "fixtures.hpp"
#include "needle_sim/brain/skull_contact.hpp"
#include "needle_sim/core/error.hpp"
#include "needle_sim/core/run_statistics.hpp"
#include "needle_sim/fem/corotational_hex_model.hpp"
#include "needle_sim/geometry/embedded_surface.hpp"
#include "needle_sim/solver/cholmod_solver.hpp"
#include "needle_sim/tissue/compliance_cache.hpp"
#include "needle_sim/tissue/tissue_body.hpp"
#include "needle_sim/tissue/tissue_loads.hpp"

using namespace needle_sim;
using needle_sim_test::clampedUnitCube;
using needle_sim_test::sourcePath;
using needle_sim_test::staticDirect;

TEST(TissueLoads, GravityBodyForceAndTractionsSumToTheirTotals) {
  // A 2 x 1 x 1 block: gravity on rho V, a body force on V, a traction on the x = 2 face.
  const HexMesh mesh = HexMesh::box(Vec3(0, 0, 0), Vec3(2, 1, 1), Vec3i(4, 3, 2));
  TissueParameters p;
  p.material = {1000.0, 0.3, 900.0};
  p.gravity = Vec3(0, 0, -9.81);
  p.body_force = Vec3(5, 0, 0);
  TractionLoad t;
  t.region.box.min = Vec3(1.99, -0.1, -0.1);
  t.region.box.max = Vec3(2.01, 1.1, 1.1);
  t.traction = Vec3(0, 7, 0);
  p.tractions.push_back(t);
  const CorotationalHexModel model(mesh, p.material);
  const VecX f = tissueLoads(mesh, model.nodalVolume(), p, "test.yaml");
  Vec3 total = Vec3::Zero();
  for (int i = 0; i < mesh.numNodes(); ++i) total += node3(f, i);
  const double V = 2.0, A = 1.0;
  EXPECT_NEAR(total.x(), 5 * V, 1e-12);
  EXPECT_NEAR(total.y(), 7 * A, 1e-12);
  EXPECT_NEAR(total.z(), -9.81 * 900 * V, 1e-9);
  // The traction's force sits on the face's nodes only.
  for (int i = 0; i < mesh.numNodes(); ++i) {
    if (mesh.node(i).x() < 1.99) {
      EXPECT_EQ(f[3 * i + 1], 0.0) << i;
    }
  }
  // A region that holds no boundary face is refused with its key among the tissue's
  // parameters (the scene loader's caller adds the section, "tissue.").
  p.tractions[0].region.box.min = Vec3(0.9, 0.4, 0.4);
  p.tractions[0].region.box.max = Vec3(1.1, 0.6, 0.6);
  try {
    tissueLoads(mesh, model.nodalVolume(), p, "test.yaml");
    FAIL() << "no InputError";
  } catch (const InputError& e) {
    EXPECT_EQ(e.key(), "tractions[0].region");
  }
}

TEST(TissueLoads, DirichletMovesAndMarksOnlyTheSelectedComponents) {
  const HexMesh mesh = HexMesh::box(Vec3(0, 0, 0), Vec3(1, 1, 1), Vec3i(2, 2, 2));
  DirichletCondition dc;
  dc.region.box.min = Vec3(0.99, -0.1, -0.1);
  dc.region.box.max = Vec3(1.01, 1.1, 1.1);
  dc.displacement = Vec3(1e-3, 2e-3, 0);
  dc.components = {true, true, false};
  VecX x = mesh.restPositions();
  const auto pre = prescribeDirichlet(mesh, {dc}, "", x);
  int marked = 0;
  for (int i = 0; i < mesh.numNodes(); ++i) {
    const bool on = mesh.node(i).x() > 0.99;
    EXPECT_EQ(pre[3 * i], on);
    EXPECT_EQ(pre[3 * i + 1], on);
    EXPECT_EQ(pre[3 * i + 2], 0);
    marked += on;
    EXPECT_DOUBLE_EQ(x[3 * i], mesh.node(i).x() + (on ? 1e-3 : 0.0));
    EXPECT_DOUBLE_EQ(x[3 * i + 1], mesh.node(i).y() + (on ? 2e-3 : 0.0));
  }
  EXPECT_EQ(marked, 9);
}

TEST(ComplianceCache, ColumnsAreThoseOfTheInverseAndStaleOnesRefreshAFewAtATime) {
  // A small SPD matrix: tridiagonal 4 on the diagonal, -1 beside it.
  const int n = 40;
  SparseMatrix A(n, n);
  std::vector<Eigen::Triplet<double>> t;
  for (int i = 0; i < n; ++i) {
    t.emplace_back(i, i, 4.0);
    if (i + 1 < n) t.emplace_back(i, i + 1, -1.0);  // upper triangle, as the solver takes it
  }
  A.setFromTriplets(t.begin(), t.end());
  CholmodSolver chol;
  chol.analyze(A);
  ASSERT_TRUE(chol.factorize(A));
  ComplianceCache cache;
  std::vector<int> dofs;
  for (int i = 0; i < 20; ++i) dofs.push_back(2 * i);
  cache.prepare(dofs, chol, chol.factorizations(), n);
  Eigen::MatrixXd full = Eigen::MatrixXd(A);
  full = full.selfadjointView<Eigen::Upper>();
  for (int f : dofs) {
    const VecX e = VecX::Unit(n, f);
    EXPECT_LT((full * cache.column(f) - e).norm(), 1e-12) << f;
    EXPECT_EQ(cache.version(f), 1);
  }
  // After a refactorisation, one prepare refreshes at most kRefresh stale columns (the
  // oldest first), not all twenty.
  ASSERT_TRUE(chol.factorize(A));
  cache.prepare(dofs, chol, chol.factorizations(), n);
  int fresh = 0;
  for (int f : dofs) fresh += cache.version(f) == 2;
  EXPECT_EQ(fresh, ComplianceCache::kRefresh);
  for (int k = 0; k < 3; ++k) cache.prepare(dofs, chol, chol.factorizations(), n);
  fresh = 0;
  for (int f : dofs) fresh += cache.version(f) == 2;
  EXPECT_EQ(fresh, 20);
}

TEST(StaticNewton, ALinearLoadConvergesAndTheLoadControlReachesItsDisplacement) {
  // A clamped cube under a small body force: Newton converges; load control finds the scale
  // that moves the centre node by a prescribed distance, and the state equals the plain
  // solve at that scale.
  // (Tolerance 1e-9: the residual's round-off floor is about 2e-11 here.)
  const HexMesh mesh = HexMesh::box(Vec3(0, 0, 0), Vec3(1, 1, 1), Vec3i(4, 4, 4));
  TissueParameters p = clampedUnitCube(1000.0, 0.3);
  TissueBody body(mesh, p, staticDirect(1e-9));
  VecX unit = VecX::Zero(mesh.numDofs());
  for (int i = 0; i < mesh.numNodes(); ++i) unit[3 * i + 2] = -1e-3;
  body.addExternalForce(unit);
  const StepStats st = body.solveStatic();
  EXPECT_LE(st.newton_iterations, 4);
  int centre = -1;
  for (int i = 0; i < mesh.numNodes(); ++i)
    if ((mesh.node(i) - Vec3(0.5, 0.5, 0.5)).norm() < 1e-12) centre = i;
  ASSERT_GE(centre, 0);
  const double u1 = -body.displacements()[3 * centre + 2];
  ASSERT_GT(u1, 0);

  TissueBody controlled(mesh, p, staticDirect(1e-9));
  controlled.addExternalForce(unit);
  LoadControl lc;
  lc.unit = &unit;
  lc.scale = 1.0;
  lc.tolerance = 1e-6 * u1;
  lc.constraint = [&](const VecX& x, VecX& g) {
    g[3 * centre + 2] = -1.0;
    return -(x[3 * centre + 2] - mesh.node(centre).z()) - 2.5 * u1;
  };
  try {
    controlled.solveStatic({}, 1e-9, 50, &lc);
  } catch (const std::exception& e) {
    FAIL() << e.what();
  }
  EXPECT_NEAR(lc.scale, 2.5, 1e-4);  // linear at these strains
  TissueBody plain(mesh, p, staticDirect(1e-9));
  plain.addExternalForce(lc.scale * unit);
  plain.solveStatic();
  EXPECT_LT((plain.displacements() - controlled.displacements()).norm(), 1e-6 * plain.displacements().norm());
}

TEST(SkullContact, GapsPenaltyAndFrozenReactionsOfASphere) {
  // The unit sphere embedded in a box: at rest every gap is -c; a uniform outward push of
  // 2c makes every vertex penetrate by c, and the frozen reactions then point inwards.
  const TriangleMesh sphere = loadTriangleMesh(sourcePath("test/data/meshes/sphere.obj"), SurfaceTransform{}, "", "");
  const auto surface = std::make_shared<const TriangleMesh>(sphere);
  const Vec3 lo = surface->boundsMin() - Vec3::Constant(0.2), hi = surface->boundsMax() + Vec3::Constant(0.2);
  const HexMesh mesh = HexMesh::box(lo, hi, Vec3i(6, 6, 6));
  const EmbeddedSurface organ(surface, mesh);
  const double c = 0.01 * (surface->boundsMax() - surface->boundsMin()).x();
  SkullContact skull(organ, nullptr, c, 1000.0);
  skull.setRest(mesh);
  const VecX X = mesh.restPositions();
  for (int v = 0; v < skull.numVertices(); ++v) EXPECT_NEAR(skull.gap(v, mesh, X), -c, 1e-12);
  int active = -1;
  EXPECT_NEAR(skull.penetration(mesh, X, active), 0.0, 0.0);
  EXPECT_EQ(active, 0);
  // A uniform dilation about the centre moves the vertices outwards by about 3c.
  const Vec3 centre = 0.5 * (surface->boundsMin() + surface->boundsMax());
  const double r = 0.5 * (surface->boundsMax() - surface->boundsMin()).x();
  VecX x = X;
  for (int i = 0; i < mesh.numNodes(); ++i) node3(x, i) = centre + (1 + 3 * c / r) * (node3(X, i) - centre);
  const double pen = skull.penetration(mesh, x, active);
  EXPECT_EQ(active, skull.numVertices());
  EXPECT_GT(pen, 1.5 * c);
  VecX f = VecX::Zero(mesh.numDofs());
  ElementBlocks K;
  skull.addForces(mesh, x, f, K);
  EXPECT_FALSE(K.element.empty());
  Vec3 total;
  const VecX frozen = skull.freeze(mesh, x, total);
  EXPECT_LT((frozen - f).norm(), 1e-12 * f.norm());  // the same forces, kept
  EXPECT_LT(total.norm(), 1e-3 * f.norm());          // inwards from every side: they balance
  EXPECT_TRUE(skull.touching());
  for (int v = 0; v < skull.numVertices(); ++v) {
    const Vec3 out = sphere.vertex(v) - centre;
    EXPECT_LT(skull.reactions()[v].dot(out), 0.0) << v;
  }
}

// The run-statistics accumulator (core/run_statistics.hpp) that summary.json, bench, soak and
// the node's diagnostics report from: misses and their longest run over every sample, the
// percentiles over the samples kept.
TEST(RunStatistics, CountsMissesTheirLongestRunAndKeepsAWindow) {
  RunStatistics s(1.0, 4);
  for (double v : {0.5, 1.5, 2.0, 0.9, 1.1, 1.2, 1.3, 0.2, 1.0}) s.add(v);
  EXPECT_EQ(s.count(), 9);
  EXPECT_EQ(s.misses(), 5);          // 1.5 2.0 | 1.1 1.2 1.3 (1.0 is on time)
  EXPECT_EQ(s.longestMissRun(), 3);
  EXPECT_DOUBLE_EQ(s.max(), 2.0);
  EXPECT_DOUBLE_EQ(s.sum(), 9.7);
  const Percentiles p = s.percentiles();  // of the last four: 1.2 1.3 0.2 1.0
  EXPECT_DOUBLE_EQ(p.max, 1.3);
  EXPECT_DOUBLE_EQ(p.median, 1.1);
  EXPECT_DOUBLE_EQ(p.mean, 0.925);
  s.clear();
  EXPECT_EQ(s.count(), 0);
  EXPECT_EQ(s.misses(), 0);
  s.add(3);
  EXPECT_EQ(s.longestMissRun(), 1);
  RunStatistics none;  // no deadline: nothing misses
  none.add(1e9);
  EXPECT_EQ(none.misses(), 0);
}

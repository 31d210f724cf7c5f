// Patch tests (doc/verification.md): on a mesh with distorted interior elements, boundary nodes
// prescribed to a linear field x = F X + c, the static solution reproduces the field at
// every interior node to 1e-10 relative, for a small strain and for a finite rotation
// combined with a stretch (the corotational element must pass both).
#include <gtest/gtest.h>

#include <random>

#include "fixtures.hpp"
#include "needle_sim/scene/scene.hpp"
#include "needle_sim/tissue/tissue_body.hpp"

using namespace needle_sim;

namespace {

HexMesh distortedBox(unsigned seed) {
  HexMesh mesh = HexMesh::box(Vec3(0, 0, 0), Vec3(1, 1, 1), Vec3i(3, 3, 3));
  std::mt19937 g(seed);
  std::uniform_real_distribution<double> U(-0.08, 0.08);
  for (int i = 0; i < mesh.numNodes(); ++i) {
    const Vec3 p = mesh.node(i);
    const bool boundary = (p.array() < 1e-12).any() || (p.array() > 1 - 1e-12).any();
    if (!boundary) mesh.setNode(i, p + Vec3(U(g), U(g), U(g)));
  }
  return mesh;
}

// All six faces prescribed (the values are replaced by the linear field below).
TissueParameters patchScene() { return needle_sim_test::clampedUnitCube(1000.0, 0.3, 1.0); }

void runPatch(const Mat3& F, const Vec3& c, double tol) {
  SolverSettings solver;
  solver.mode = SolverSettings::Mode::Static;
  solver.static_tolerance = 1e-13;
  solver.static_max_iterations = 200;
  solver.linear.method = LinearSolverSettings::Method::Direct;
  TissueBody body(distortedBox(42), patchScene(), solver);
  const HexMesh& mesh = body.mesh();
  VecX target(mesh.numDofs());
  for (int i = 0; i < mesh.numNodes(); ++i) target.segment<3>(3 * i) = F * mesh.node(i) + c;
  body.setPrescribedPositions(target);
  ASSERT_EQ(body.dofs().numFree(), 3 * 8);  // the 8 interior nodes
  body.solveStatic();
  const double err = (body.positions() - target).lpNorm<Eigen::Infinity>();
  const double scale = (target - mesh.restPositions()).lpNorm<Eigen::Infinity>();
  EXPECT_LT(err, tol * scale) << "max nodal error " << err;
}

}  // namespace

TEST(PatchTest, SmallLinearFieldIsReproducedExactly) {
  Mat3 A;
  A << 1e-3, 2e-4, -3e-4, 5e-4, -2e-3, 1e-4, 0.0, 3e-4, 1.5e-3;
  runPatch(Mat3::Identity() + A, Vec3(1e-3, -2e-3, 5e-4), 1e-10);
}

TEST(PatchTest, FiniteRotationWithStretchIsReproducedExactly) {
  Mat3 U;
  U << 1.05, 0.02, 0.0, 0.02, 0.97, 0.01, 0.0, 0.01, 1.02;  // symmetric stretch
  const Mat3 Q = Eigen::AngleAxisd(0.6, Vec3(1, 1, 0).normalized()).toRotationMatrix();
  runPatch(Q * U, Vec3(0.1, 0.2, -0.1), 1e-10);
}

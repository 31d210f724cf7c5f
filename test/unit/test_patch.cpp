// Patch tests (doc/verification.md): on a mesh with distorted interior elements, boundary nodes
// prescribed to a linear field x = F X + c, the static solution reproduces the field at
// every interior node to 1e-10 relative, for a small strain and for a finite rotation
// combined with a stretch (the corotational element must pass both), with every hexahedron
// formulation (tissue.element) and up to nu = 0.4999 (#37: a B-bar or incompatible-mode
// element that failed the patch test on distorted cells would converge to a wrong answer).
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
TissueParameters patchScene(HexFormulation element, double nu) {
  TissueParameters t = needle_sim_test::clampedUnitCube(1000.0, nu, 1.0);
  t.material.element = element;
  return t;
}

struct Case {
  HexFormulation element;
  double nu;
};
const Case kCases[] = {{HexFormulation::Trilinear, 0.3},
                       {HexFormulation::Trilinear, 0.4999},
                       {HexFormulation::Bbar, 0.3},
                       {HexFormulation::Bbar, 0.4999},
                       {HexFormulation::IncompatibleModes, 0.3},
                       {HexFormulation::IncompatibleModes, 0.4999},
                       {HexFormulation::IncompatibleModesBbar, 0.3},
                       {HexFormulation::IncompatibleModesBbar, 0.499},
                       {HexFormulation::IncompatibleModesBbar, 0.4999}};

void runPatch(const Mat3& F, const Vec3& c, double tol) {
  for (const Case& k : kCases) {
    SCOPED_TRACE("element " + std::to_string(static_cast<int>(k.element)) + ", nu " + std::to_string(k.nu));
  SolverSettings solver;
  solver.mode = SolverSettings::Mode::Static;
  solver.static_tolerance = 1e-13;
  solver.static_max_iterations = 200;
  solver.linear.method = LinearSolverSettings::Method::Direct;
  TissueBody body(distortedBox(42), patchScene(k.element, k.nu), solver);
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
}

}  // namespace

TEST(PatchTest, SmallLinearFieldIsReproducedExactly) {
  Mat3 A;
  A << 1e-3, 2e-4, -3e-4, 5e-4, -2e-3, 1e-4, 0.0, 3e-4, 1.5e-3;
  runPatch(Mat3::Identity() + A, Vec3(1e-3, -2e-3, 5e-4), 1e-10);
}

TEST(PatchTest, FiniteRotationWithStretchIsReproducedExactly) {
  Mat3 U;
  // A symmetric stretch with trace 3: no volume strain in the corotated frame. (At nu = 0.4999 a
  // 4 % volume change would be a pressure of 200 mu, whose geometric stiffness Newton with
  // R K0 R^T alone does not see: it would stall, whatever the element.)
  U << 1.05, 0.02, 0.0, 0.02, 0.93, 0.01, 0.0, 0.01, 1.02;
  const Mat3 Q = Eigen::AngleAxisd(0.6, Vec3(1, 1, 0).normalized()).toRotationMatrix();
  runPatch(Q * U, Vec3(0.1, 0.2, -0.1), 1e-10);
}

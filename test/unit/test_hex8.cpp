// The hex8 element in isolation: shape functions, reference stiffness, mass weights.
#include <gtest/gtest.h>

#include <Eigen/Eigenvalues>
#include <array>
#include <random>

#include "needle_sim/fem/embedded_point.hpp"
#include "needle_sim/fem/hex8.hpp"

using namespace needle_sim;

namespace {
hex8::Mat83 boxCorners(const Eigen::Vector3d& lo, const Eigen::Vector3d& hi) {
  hex8::Mat83 X;
  for (int a = 0; a < 8; ++a)
    for (int d = 0; d < 3; ++d) X(a, d) = hex8::kCornerSigns[a][d] < 0 ? lo[d] : hi[d];
  return X;
}
}  // namespace

TEST(Hex8, ShapeFunctionsInterpolateNodesAndSumToOne) {
  for (int a = 0; a < 8; ++a) {
    const Eigen::Vector3d xi(hex8::kCornerSigns[a][0], hex8::kCornerSigns[a][1], hex8::kCornerSigns[a][2]);
    const auto N = hex8::shape(xi);
    for (int b = 0; b < 8; ++b) EXPECT_DOUBLE_EQ(N[b], a == b ? 1.0 : 0.0);
  }
  const Eigen::Vector3d xi(0.3, -0.7, 0.1);
  EXPECT_NEAR(hex8::shape(xi).sum(), 1.0, 1e-15);
  EXPECT_LT(hex8::shapeGradNatural(xi).colwise().sum().norm(), 1e-15);
}

TEST(Hex8, ReferenceStiffnessHasExactlySixRigidModes) {
  LinearElasticMaterial m{2.0e5, 0.3, 1000};
  const auto ref = hex8::computeReference(boxCorners({0, 0, 0}, {0.2, 0.1, 0.3}), m);
  EXPECT_NEAR(ref.volume, 0.2 * 0.1 * 0.3, 1e-15);
  EXPECT_NEAR(ref.node_volume.sum(), ref.volume, 1e-15);
  EXPECT_LT((ref.K0 - ref.K0.transpose()).norm(), 1e-12 * ref.K0.norm());
  Eigen::SelfAdjointEigenSolver<hex8::Mat24> es(ref.K0);
  const auto ev = es.eigenvalues();
  const double scale = ev.maxCoeff();
  int zeros = 0;
  for (int i = 0; i < 24; ++i) {
    EXPECT_GT(ev[i], -1e-12 * scale);
    if (std::abs(ev[i]) < 1e-10 * scale) ++zeros;
  }
  EXPECT_EQ(zeros, 6);  // 3 translations + 3 infinitesimal rotations
}

TEST(Hex8, ConstantStrainGivesExactStressResultant) {
  // Uniaxial strain eps_xx on a box: the nodal forces on the x = hi face sum to
  // sigma_xx * area with sigma_xx = (lambda + 2 mu) eps for a laterally fixed box... here we
  // use the uniaxial-stress field (lateral contraction nu*eps) so sigma_xx = E eps exactly.
  LinearElasticMaterial m{1000.0, 0.25, 1};
  const double lx = 2, ly = 0.5, lz = 0.7, eps = 1e-3;
  const auto X = boxCorners({0, 0, 0}, {lx, ly, lz});
  const auto ref = hex8::computeReference(X, m);
  Eigen::Matrix<double, 24, 1> u;
  for (int a = 0; a < 8; ++a) u.segment<3>(3 * a) << eps * X(a, 0), -m.poisson * eps * X(a, 1), -m.poisson * eps * X(a, 2);
  const Eigen::Matrix<double, 24, 1> f = ref.K0 * u;
  double fx = 0;
  for (int a = 0; a < 8; ++a)
    if (X(a, 0) > 0) fx += f[3 * a];
  EXPECT_NEAR(fx, m.young * eps * ly * lz, 1e-12);
  for (int a = 0; a < 8; ++a) {
    EXPECT_NEAR(f[3 * a + 1], 0.0, 1e-12);
    EXPECT_NEAR(f[3 * a + 2], 0.0, 1e-12);
  }
}

TEST(Hex8, InverseMapRecoversNaturalCoordinates) {
  hex8::Mat83 X = boxCorners({0, 0, 0}, {1, 1, 1});
  X(6, 0) += 0.3;  // distort one corner
  X(6, 2) -= 0.2;
  const Eigen::Vector3d xi(0.2, -0.5, 0.7);
  const Eigen::Vector3d p = X.transpose() * hex8::shape(xi);
  Eigen::Vector3d back;
  ASSERT_TRUE(hex8::inverseMap(X, p, back));
  EXPECT_LT((back - xi).norm(), 1e-12);
}

// The locator passes over a bin's elements whose bounding box (widened a little beyond the
// 1e-9 tolerance in xi) does not hold the point, before inverting the map: the elements it
// finds and misses are those a search of every element finds and misses, on a distorted
// block, at random points, on element faces and corners, and a rounding error outside.
TEST(Hex8, PointLocatorFindsWhatASearchOfEveryElementFinds) {
  std::array<Eigen::Vector3d, 8> corners;
  for (int a = 0; a < 8; ++a)
    for (int d = 0; d < 3; ++d) corners[a][d] = hex8::kCornerSigns[a][d] < 0 ? 0.0 : 1.0;
  corners[6] += Eigen::Vector3d(0.3, -0.2, 0.25);
  corners[3] += Eigen::Vector3d(-0.1, 0.15, 0.05);
  const HexMesh mesh = HexMesh::mappedBlock(corners, Vec3i(4, 3, 5));
  const PointLocator locator(mesh);
  auto inside = [&](const Vec3& p, int e) {
    Eigen::Vector3d xi;
    return hex8::inverseMap(mesh.elementCorners(e), p, xi) && xi.cwiseAbs().maxCoeff() <= 1 + 1e-9;
  };
  std::vector<Vec3> points;
  std::mt19937 g(7);
  const Vec3 lo = mesh.boundsMin(), hi = mesh.boundsMax();
  std::uniform_real_distribution<double> U(0, 1);
  for (int k = 0; k < 2000; ++k) points.push_back(lo + (hi - lo).cwiseProduct(Vec3(U(g), U(g), U(g))));
  for (int e = 0; e < mesh.numElements(); ++e) {
    const auto X = mesh.elementCorners(e);
    for (const Vec3& xi : {Vec3(1, 0.3, -0.2), Vec3(-1, -1, -1), Vec3(1, 1, 1), Vec3(0.5, -1, 1)})
      for (double out : {0.0, 1e-12, 1e-6}) points.push_back(X.transpose() * hex8::shape(xi * (1 + out)));
  }
  int found = 0, missed = 0;
  for (const Vec3& p : points) {
    bool any = false;
    for (int e = 0; e < mesh.numElements() && !any; ++e) any = inside(p, e);
    EmbeddedPoint ep;
    const bool located = locator.locate(p, ep);
    ASSERT_EQ(located, any) << p.transpose();
    if (!located) {
      ++missed;
      continue;
    }
    ++found;
    EXPECT_TRUE(inside(p, ep.element));
    EXPECT_LT((ep.interpolate(mesh, mesh.restPositions()) - p).norm(), 1e-9);
  }
  EXPECT_GT(found, 1000);
  EXPECT_GT(missed, 100);  // the block is distorted: its bounding box holds points outside it
}

TEST(Hex8, DegenerateElementIsRejected) {
  hex8::Mat83 X = boxCorners({0, 0, 0}, {1, 1, 1});
  X.col(2).setZero();  // flat
  LinearElasticMaterial m{1, 0.3, 1};
  EXPECT_THROW(hex8::computeReference(X, m), std::invalid_argument);
}

namespace {
// A skewed, tapered hexahedron (no two faces parallel).
hex8::Mat83 distortedCorners() {
  hex8::Mat83 X = boxCorners({0, 0, 0}, {0.2, 0.1, 0.3});
  const double d[8][3] = {{0.01, -0.005, 0.02}, {0.03, 0.01, -0.01}, {-0.02, 0.02, 0.0},  {0.0, -0.01, 0.015},
                          {0.02, 0.0, -0.02},   {-0.01, 0.015, 0.03}, {0.015, -0.02, 0.01}, {-0.03, 0.005, -0.01}};
  for (int a = 0; a < 8; ++a)
    for (int k = 0; k < 3; ++k) X(a, k) += d[a][k];
  return X;
}
const HexFormulation kFormulations[] = {HexFormulation::Trilinear, HexFormulation::Bbar,
                                        HexFormulation::IncompatibleModes, HexFormulation::IncompatibleModesBbar};
std::string name(HexFormulation f) { return std::to_string(static_cast<int>(f)); }
}  // namespace

// Every formulation (#37), on a distorted element, at a compressible and a nearly
// incompressible nu: K0 symmetric, positive semi-definite, exactly six zero eigenvalues (no
// spurious zero-energy mode from the condensed modes or the mean dilatation).
TEST(Hex8, EveryFormulationHasExactlySixRigidModes) {
  for (HexFormulation f : kFormulations)
    for (double nu : {0.3, 0.4999}) {
      SCOPED_TRACE("formulation " + name(f) + ", nu " + std::to_string(nu));
      LinearElasticMaterial m{2.0e5, nu, 1000, f};
      const auto ref = hex8::computeReference(distortedCorners(), m);
      EXPECT_LT((ref.K0 - ref.K0.transpose()).norm(), 1e-12 * ref.K0.norm());
      Eigen::SelfAdjointEigenSolver<hex8::Mat24> es(ref.K0);
      const auto ev = es.eigenvalues();
      // The smallest deformation mode's eigenvalue is ~mu h; lambda only enlarges the largest.
      const double scale = m.lameMu() * 0.2;
      int zeros = 0;
      for (int i = 0; i < 24; ++i) {
        EXPECT_GT(ev[i], -1e-9 * scale);
        if (std::abs(ev[i]) < 1e-9 * scale) ++zeros;
      }
      EXPECT_EQ(zeros, 6);
      EXPECT_GT(ev[6], 1e-3 * scale);
    }
}

// The strain operator is the one the stiffness integrates: K0 = sum_q E_q^T D E_q det J_q at
// the 2x2x2 Gauss points (for the modes: the condensed stiffness equals the energy of the
// condensed strain), so stresses, SPR and the goal duals see the element's own strains.
TEST(Hex8, StrainOperatorIsTheOneTheStiffnessIntegrates) {
  const auto X = distortedCorners();
  const double g = 1.0 / std::sqrt(3.0);
  for (HexFormulation f : kFormulations)
    for (double nu : {0.3, 0.499}) {
      SCOPED_TRACE("formulation " + name(f) + ", nu " + std::to_string(nu));
      LinearElasticMaterial m{2.0e5, nu, 1000, f};
      const auto ref = hex8::computeReference(X, m);
      hex8::Mat24 K = hex8::Mat24::Zero();
      Eigen::Matrix<double, 1, 24> mean = Eigen::Matrix<double, 1, 24>::Zero();
      for (int q = 0; q < 8; ++q) {
        const Eigen::Vector3d xi(hex8::kCornerSigns[q][0] * g, hex8::kCornerSigns[q][1] * g, hex8::kCornerSigns[q][2] * g);
        const double detJ = (X.transpose() * hex8::shapeGradNatural(xi)).determinant();
        const auto E = hex8::strainOperator(X, ref, xi);
        K += E.transpose() * m.elasticity() * E * detJ;
        mean += E.topRows<3>().colwise().sum() * detJ;
      }
      EXPECT_LT((K - ref.K0).norm(), 1e-12 * ref.K0.norm());
      // Every formulation keeps the element's volume change: the mean dilatation is the
      // trilinear one (the modes' mean is zero; B-bar replaces the pointwise one by it).
      EXPECT_LT((mean / ref.volume - ref.mean_dilatation).norm(), 1e-12 * ref.mean_dilatation.norm());
      if (f == HexFormulation::Bbar) {  // the volume strain is the mean everywhere
        const auto E = hex8::strainOperator(X, ref, Eigen::Vector3d(0.3, -0.6, 0.2));
        EXPECT_LT((E.topRows<3>().colwise().sum() - ref.mean_dilatation).norm(), 1e-12 * ref.mean_dilatation.norm());
      }
    }
}

// Wilson's incompatible modes make a rectangular element exact in pure bending: one element
// under the end moment of a linear bending stress bends as the beam does (u_y = -eps x^2 /
// (2 h) ...), the trilinear one locks in shear (its bending energy is too high).
TEST(Hex8, IncompatibleModesBendExactlyTrilinearLocks) {
  const double L = 4, h = 1, t = 1;  // one 4 x 1 x 1 element, bending about z
  const auto X = boxCorners({0, -h / 2, 0}, {L, h / 2, t});
  const double kappa = 1e-3;  // curvature: u_x = -kappa x y
  Eigen::Matrix<double, 24, 1> u;
  for (int a = 0; a < 8; ++a) u.segment<3>(3 * a) << -kappa * X(a, 0) * X(a, 1), 0.5 * kappa * X(a, 0) * X(a, 0), 0;
  const double E = 1000;
  for (HexFormulation f : {HexFormulation::Trilinear, HexFormulation::IncompatibleModes}) {
    LinearElasticMaterial m{E, 0.0, 1, f};
    const auto ref = hex8::computeReference(X, m);
    const double energy = 0.5 * u.dot(ref.K0 * u);
    const double beam = 0.5 * E * (t * h * h * h / 12) * kappa * kappa * L;  // 1/2 E I kappa^2 L
    if (f == HexFormulation::Trilinear)
      EXPECT_GT(energy, 2.0 * beam);  // shear locking: (1 + (L/h)^2 / 2 ...) times too stiff
    else
      EXPECT_NEAR(energy, beam, 1e-10 * beam);
  }
}

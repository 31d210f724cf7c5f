// The corotational element: invariance under rigid motion, consistency of the matrix-free
// stiffness product with the assembled one, robustness on inverted elements.
#include <gtest/gtest.h>

#include <array>
#include <random>

#include "needle_sim/fem/corotational_hex_model.hpp"

using namespace needle_sim;

namespace {
struct Fixture {
  HexMesh mesh = HexMesh::box(Vec3(0, 0, 0), Vec3(0.04, 0.02, 0.02), Vec3i(4, 2, 2));
  LinearElasticMaterial mat{1e7, 0.4, 1000};
  CorotationalHexModel model{mesh, mat};
  VecX rest = mesh.restPositions();

  VecX deformed(unsigned seed, double amp) const {
    std::mt19937 g(seed);
    std::uniform_real_distribution<double> U(-amp, amp);
    VecX x = rest;
    for (int i = 0; i < x.size(); ++i) x[i] += U(g);
    return x;
  }
  static VecX transform(const VecX& x, const Mat3& Q, const Vec3& t) {
    VecX y(x.size());
    for (int i = 0; i < x.size() / 3; ++i) y.segment<3>(3 * i) = Q * x.segment<3>(3 * i) + t;
    return y;
  }
};
}  // namespace

TEST(Corotational, RigidMotionProducesNoForce) {
  Fixture f;
  const Mat3 Q = Eigen::AngleAxisd(M_PI / 2, Vec3(1, 2, 3).normalized()).toRotationMatrix();
  const VecX x = Fixture::transform(f.rest, Q, Vec3(0.1, -0.2, 0.05));
  f.model.updateRotations(x);
  VecX force = VecX::Zero(x.size());
  f.model.addInternalForce(x, force);
  // Scale: force of a 1 % strain on one element face, E * eps * h^2.
  const double scale = f.mat.young * 0.01 * 0.01 * 0.01;
  EXPECT_LT(force.lpNorm<Eigen::Infinity>(), 1e-9 * scale);
  for (int e = 0; e < f.model.numElements(); ++e) EXPECT_LT((f.model.rotation(e) - Q).norm(), 1e-10);
  EXPECT_LT(f.model.elasticEnergy(x), 1e-20);
}

TEST(Corotational, ForcesRotateWithTheBody) {
  Fixture f;
  const VecX x = f.deformed(7, 0.001);  // up to 1 mm on 1 cm elements: large strains
  f.model.updateRotations(x);
  VecX f0 = VecX::Zero(x.size());
  f.model.addInternalForce(x, f0);
  const double E0 = f.model.elasticEnergy(x);

  const Mat3 Q = Eigen::AngleAxisd(M_PI / 2, Vec3(0, 0, 1)).toRotationMatrix();
  const VecX y = Fixture::transform(x, Q, Vec3(1, 2, 3));
  f.model.updateRotations(y);
  VecX f1 = VecX::Zero(x.size());
  f.model.addInternalForce(y, f1);
  const VecX f0rot = Fixture::transform(f0, Q, Vec3::Zero());
  EXPECT_GT(f0.norm(), 0);
  EXPECT_LT((f1 - f0rot).norm(), 1e-9 * f0.norm());
  EXPECT_NEAR(f.model.elasticEnergy(y), E0, 1e-9 * E0);
}

TEST(Corotational, MatrixFreeProductMatchesAssembledElements) {
  Fixture f;
  const VecX x = f.deformed(3, 0.0005);
  f.model.updateRotations(x);
  const VecX v = f.deformed(11, 1.0) - f.rest;
  VecX Kv = VecX::Zero(v.size());
  f.model.addStiffnessProduct(v, 2.0, Kv);
  VecX ref = VecX::Zero(v.size());
  hex8::Mat24 Ke;
  for (int e = 0; e < f.model.numElements(); ++e) {
    f.model.elementStiffness(e, Ke);
    Eigen::Matrix<double, 24, 1> ve;
    const auto& el = f.mesh.element(e);
    for (int a = 0; a < 8; ++a) ve.segment<3>(3 * a) = v.segment<3>(3 * el[a]);
    const Eigen::Matrix<double, 24, 1> w = Ke * ve;
    for (int a = 0; a < 8; ++a) ref.segment<3>(3 * el[a]) += 2.0 * w.segment<3>(3 * a);
  }
  EXPECT_LT((Kv - ref).norm(), 1e-12 * ref.norm());
}

TEST(Corotational, UniformGridSharesOneReferenceMatrix) {
  Fixture f;
  EXPECT_EQ(f.model.numReferences(), 1);
  EXPECT_NEAR(f.model.nodalVolume().sum(), 0.04 * 0.02 * 0.02, 1e-18);
}

// Cut cells (immersed grids) share their shape's reference, scaled by their volume fraction:
// one reference per distinct fraction, each the full cell's times the fraction.
TEST(Corotational, CutCellsScaleTheirShapesReference) {
  HexMesh mesh = HexMesh::box(Vec3(0, 0, 0), Vec3(0.04, 0.02, 0.02), Vec3i(4, 2, 2));
  std::vector<double> fraction(mesh.numElements());
  for (int e = 0; e < mesh.numElements(); ++e) fraction[e] = e % 3 == 0 ? 1.0 : e % 3 == 1 ? 0.25 : 0.6;
  mesh.setFractions(fraction);
  const LinearElasticMaterial mat{1e7, 0.4, 1000};
  CorotationalHexModel model(mesh, mat);
  EXPECT_EQ(model.numReferences(), 3);
  EXPECT_EQ(model.numShapes(), 1);
  double volume = 0;
  for (int e = 0; e < mesh.numElements(); ++e) {
    const hex8::ElementReference full = hex8::computeReference(mesh.elementCorners(e), mat);
    const auto& r = model.reference(e);
    EXPECT_LT((r.K0 - fraction[e] * full.K0).norm(), 1e-12 * full.K0.norm()) << e;
    EXPECT_LT((r.node_volume - fraction[e] * full.node_volume).norm(), 1e-12 * full.node_volume.norm()) << e;
    volume += fraction[e] * full.volume;
  }
  EXPECT_NEAR(model.nodalVolume().sum(), volume, 1e-12 * volume);
  // A distorted block: every element a shape of its own.
  std::array<Vec3, 8> corners;
  for (int a = 0; a < 8; ++a)
    for (int d = 0; d < 3; ++d) corners[a][d] = hex8::kCornerSigns[a][d] < 0 ? 0.0 : 1.0;
  corners[6] += Vec3(0.15, -0.1, 0.2);
  const HexMesh distorted = HexMesh::mappedBlock(corners, Vec3i(2, 2, 2));
  CorotationalHexModel each(distorted, mat);
  EXPECT_EQ(each.numReferences(), distorted.numElements());
  EXPECT_EQ(each.numShapes(), distorted.numElements());
  for (int e = 0; e < distorted.numElements(); ++e)
    EXPECT_LT((each.reference(e).K0 - hex8::computeReference(distorted.elementCorners(e), mat).K0).norm(),
              1e-12 * each.reference(e).K0.norm());
}

TEST(Corotational, InvertedElementGivesProperRotationAndFiniteForces) {
  HexMesh mesh = HexMesh::box(Vec3(0, 0, 0), Vec3(1, 1, 1), Vec3i(1, 1, 1));
  LinearElasticMaterial mat{1, 0.3, 1};
  CorotationalHexModel model(mesh, mat);
  VecX x = mesh.restPositions();
  for (int a = 4; a < 8; ++a) x[3 * a + 2] = -0.5;  // push the top face through the bottom
  model.updateRotations(x);
  EXPECT_EQ(model.invertedElements(), 1);
  const Mat3 R = model.rotation(0);
  EXPECT_LT((R.transpose() * R - Mat3::Identity()).norm(), 1e-12);
  EXPECT_NEAR(R.determinant(), 1.0, 1e-12);
  VecX force = VecX::Zero(x.size());
  model.addInternalForce(x, force);
  EXPECT_TRUE(force.allFinite());
  // The restoring force pushes the top face back up.
  double fz_top = 0;
  for (int a = 4; a < 8; ++a) fz_top += force[3 * a + 2];
  EXPECT_GT(fz_top, 0);
}

// The rotation part of the tangent (RotationTerms) completes R K0 R^T to the derivative of
// the internal force: (R K0 R^T + K_rot) v = -(f(x + e v) - f(x - e v)) / 2e, the rotations
// recomputed at each side. Without K_rot the difference is of the size of the stresses times
// the rotations, which the check must see (it could fail: a sign or a transpose off).
TEST(Corotational, RotationTermsCompleteTheConsistentTangent) {
  Fixture f;
  // A large deformation: turned by 40 degrees, nodes moved by up to 1 mm on 1 cm elements.
  const Mat3 Q = Eigen::AngleAxisd(0.7, Vec3(1, -2, 0.5).normalized()).toRotationMatrix();
  const VecX x = Fixture::transform(f.deformed(5, 0.001), Q, Vec3(0.01, 0, 0));
  const VecX v = f.deformed(13, 1.0) - f.rest;
  auto force = [&](const VecX& y) {
    f.model.updateRotations(y);
    VecX g = VecX::Zero(y.size());
    f.model.addInternalForce(y, g);
    return g;
  };
  const double eps = 1e-7;
  const VecX fd = -(force(x + eps * v) - force(x - eps * v)) / (2 * eps);
  f.model.updateRotations(x);
  VecX plain = VecX::Zero(v.size());
  f.model.addStiffnessProduct(v, 1.0, plain);
  CorotationalHexModel::RotationTerms t;
  f.model.rotationTerms(x, t);
  VecX full = plain;
  f.model.addRotationStiffnessProduct(t, v, 1.0, full);
  EXPECT_LT((full - fd).norm(), 1e-6 * fd.norm());
  EXPECT_GT((plain - fd).norm(), 1e-2 * fd.norm());
  // A rigid rotation's spin turns the forces: K v = w x f for v = w x x.
  const Vec3 w(0.3, -0.2, 0.9);
  VecX spin(x.size()), turned(x.size());
  const VecX f0 = force(x);
  for (int i = 0; i < x.size() / 3; ++i) {
    spin.segment<3>(3 * i) = w.cross(Vec3(x.segment<3>(3 * i)));
    turned.segment<3>(3 * i) = -w.cross(Vec3(f0.segment<3>(3 * i)));
  }
  VecX k = VecX::Zero(x.size());
  f.model.addStiffnessProduct(spin, 1.0, k);
  f.model.addRotationStiffnessProduct(t, spin, 1.0, k);
  EXPECT_LT((k - turned).norm(), 1e-9 * f0.norm());
}

// The interaction's geometric pieces on their own: the needle's Hermite centre line
// (centre_line.hpp), needles in needles (sheath.hpp), and the constraint rows
// (constraint_rows.hpp): H applied to the bodies' velocities is the relative velocity of
// the two material points along each row.
#include <gtest/gtest.h>

#include <Eigen/Eigenvalues>

#include <cmath>
#include <memory>

#include "fixtures.hpp"
#include "needle_sim/contact/centre_line.hpp"
#include "needle_sim/contact/constraint_rows.hpp"
#include "needle_sim/contact/sheath.hpp"
#include "needle_sim/contact/shaft_constraint.hpp"
#include "needle_sim/fem/embedded_point.hpp"
#include "needle_sim/needle/needle_body.hpp"
#include "needle_sim/tissue/tissue_body.hpp"

using namespace needle_sim;

namespace {

NeedleParameters needle(const std::string& name, double radius, double inner, const Vec3& base, double length = 0.1) {
  NeedleParameters n;
  n.name = name;
  n.length = length;
  n.radius = radius;
  n.inner_radius = inner;
  n.young = 2e11;
  n.poisson = 0.3;
  n.density = 8000;
  n.elements = 10;
  n.base_position = base;
  n.base_direction = Vec3::UnitX();
  return n;
}

SolverSettings dynamic() {
  SolverSettings s;
  s.linear.method = LinearSolverSettings::Method::Direct;
  return s;
}

}  // namespace

TEST(CentreLine, HermiteBasisAndAStraightNeedle) {
  for (double xi : {0.0, 0.2, 0.5, 0.9, 1.0}) {
    const HermiteWeights h = hermite(xi);
    EXPECT_NEAR(h.h00 + h.h01, 1.0, 1e-15);  // partition of unity of the positions
    EXPECT_NEAR(h.d00 + h.d01, 0.0, 1e-15);
    // A straight segment from 0 to 1 with unit tangents reproduces x = xi.
    EXPECT_NEAR(h.h10 + h.h01 + h.h11, xi, 1e-15);
  }
  NeedleBody nd(needle("n", 1e-3, 0, Vec3(0.1, 0.2, 0.3)), dynamic());
  for (double s : {0.0, 0.013, 0.05, 0.0999, 0.1}) {
    const CentreLinePoint c = centreLinePoint(nd, s);
    EXPECT_LT((c.position - Vec3(0.1 + s, 0.2, 0.3)).norm(), 1e-14) << s;
    EXPECT_LT((c.axis - Vec3::UnitX()).norm(), 1e-14);
    EXPECT_NEAR(closestArcLength(nd, c.position + Vec3(0, 0.01, -0.02)), s, 1e-14);
  }
  // Beyond the tip the arc length goes on (a point the needle was withdrawn past), before
  // the base it stops at 0.
  EXPECT_NEAR(closestArcLength(nd, Vec3(0.25, 0.2, 0.3)), 0.15, 1e-14);
  EXPECT_EQ(closestArcLength(nd, Vec3(0.0, 0.2, 0.3)), 0.0);
  EXPECT_NEAR(distanceFromAxis(nd, 0.05, Vec3(0.15, 0.23, 0.34)), 0.05, 1e-14);
}

TEST(CentreLine, ABentNeedleFollowsTheHermiteCurve) {
  // A cantilever under a tip load bends; between nodes the centre line is the Hermite cubic,
  // which lies on the deflection curve of the beam (a cubic for an end load) to round-off.
  NeedleParameters p = needle("n", 1e-3, 0, Vec3::Zero());
  p.tip_force = Vec3(0, 1e-3, 0);
  SolverSettings s = dynamic();
  s.mode = SolverSettings::Mode::Static;
  s.static_tolerance = 1e-12;
  s.static_max_iterations = 100;
  NeedleBody nd(p, s);
  nd.solveStatic(0);
  const double L = p.length, EI = p.young * M_PI * std::pow(p.radius, 4) / 4, P = 1e-3;
  for (double x : {0.005, 0.037, 0.061, 0.093}) {
    const double w = P * x * x * (3 * L - x) / (6 * EI);  // exact end-load deflection
    const CentreLinePoint c = centreLinePoint(nd, x);
    EXPECT_NEAR(c.position.y(), w, 1e-3 * w + 1e-12) << x;  // (the beam is corotational: tiny rotations here)
  }
}

TEST(Sheath, AnElectrodeInsideACannulaIsSheathedAndShaftPointsFindTheNeedleThroughThem) {
  NeedleBody cannula(needle("cannula", 1.5e-3, 1.0e-3, Vec3::Zero()), dynamic());
  NeedleBody inside(needle("electrode", 0.5e-3, 0, Vec3(-0.02, 0, 0), 0.11), dynamic());   // tip at 0.09: inside
  NeedleBody beyond(needle("electrode", 0.5e-3, 0, Vec3(0.0, 0, 0), 0.12), dynamic());     // tip at 0.12: out
  NeedleBody beside(needle("probe", 0.5e-3, 0, Vec3(-0.02, 0.01, 0), 0.11), dynamic());    // parallel, 1 cm off
  std::vector<NeedleBody*> a{&cannula, &inside}, b{&cannula, &beyond}, c{&cannula, &beside};
  EXPECT_EQ(sheathOf(a, 1, 1e-6), 0);
  EXPECT_EQ(sheathOf(a, 0, 1e-6), -1);  // the cannula is in nothing
  EXPECT_EQ(sheathOf(b, 1, 1e-6), -1);
  EXPECT_EQ(sheathOf(c, 1, 1e-6), -1);
  // A point on the cannula's axis at x = 0.05: the electrode runs through it (s = 0.07 on it).
  double s = -1;
  EXPECT_EQ(needleThrough(a, 0, Vec3(0.05, 0, 0), s), 1);
  EXPECT_NEAR(s, 0.07, 1e-12);
  EXPECT_EQ(needleThrough(c, 0, Vec3(0.05, 0, 0), s), -1);  // 1 cm away: not within the radii
}

TEST(ConstraintRows, RowsTimesVelocitiesAreTheRelativeVelocityOfThePoints) {
  // A tissue block and a needle through it; velocities: tissue in a linear field, needle
  // translating and spinning. H v equals d_k . (v_needle(point) - v_tissue(point)) row by
  // row, for shaft points on the needle between nodes.
  const HexMesh mesh = HexMesh::box(Vec3(0, -0.01, -0.01), Vec3(0.04, 0.01, 0.01), Vec3i(4, 2, 2));
  TissueParameters tp = needle_sim_test::clampedUnitCube(1e4, 0.3, 1000);
  tp.dirichlet.clear();
  TissueBody tissue(mesh, tp, dynamic());
  VecX vt(mesh.numDofs());
  const Mat3 G = (Mat3() << 0.1, 0.2, -0.3, 0.05, -0.1, 0.2, 0.3, 0.1, 0.0).finished();
  for (int i = 0; i < mesh.numNodes(); ++i) node3(vt, i) = G * mesh.node(i) + Vec3(0.01, -0.02, 0.03);
  tissue.setState(tissue.positions(), vt);
  NeedleBody nd(needle("n", 1e-3, 0, Vec3(-0.03, 0.002, -0.001), 0.06), dynamic());
  VecX vn = VecX::Zero(nd.numDofs());
  const Vec3 v0(0.02, 0.01, -0.005), w0(0.3, -0.2, 0.5);  // rigid motion about the base
  for (int k = 0; k < nd.beam().numNodes(); ++k) {
    vn.segment<3>(6 * k) = v0 + w0.cross(nd.state().p[k] - nd.state().p[0]);
    vn.segment<3>(6 * k + 3) = w0;
  }
  nd.setState(nd.state(), vn);
  // The bodies' free motion: it gives their velocity changes (zeroed here, so that the rows
  // see the velocities set above) and the factors the compliance needs.
  tissue.freeMotion(1e-3);
  tissue.addVelocityChangeFree(-tissue.velocityChangeFree());
  nd.freeMotion(0.0, 1e-3);
  VecX undo(nd.dofs().numFree());
  for (int k = 0; k < nd.dofs().numFree(); ++k) undo[k] = -nd.velocityChange()[nd.dofs().freeToFull()[k]];
  nd.addVelocityChangeFree(undo);
  std::vector<NeedleBody*> needles{&nd};
  std::vector<std::unique_ptr<ContactConstraint>> cs;
  const PointLocator locator(mesh);
  for (double s : {0.031, 0.0425, 0.057}) {
    auto c = std::make_unique<ShaftConstraint>(0.1);
    c->needle = 0;
    c->s = s;
    const CentreLinePoint cl = centreLinePoint(nd, s);
    ASSERT_TRUE(locator.locate(cl.position, c->tissue));
    c->frame.col(0) = cl.axis;
    c->frame.col(1) = cl.axis.unitOrthogonal();
    c->frame.col(2) = cl.axis.cross(c->frame.col(1));
    cs.push_back(std::move(c));
  }
  std::vector<int> column_of(tissue.dofs().numFree(), -1);
  ConstraintRows rows;
  rows.build(cs, tissue, needles, column_of);
  for (int f : column_of) EXPECT_EQ(f, -1);  // scratch left clean
  const VecX u = rows.freeVelocity(tissue, needles);
  ASSERT_EQ(u.size(), 9);
  for (int p = 0; p < 3; ++p) {
    const auto& c = *cs[p];
    const Vec3 x = centreLinePoint(nd, c.s).position;
    const Vec3 v_needle = v0 + w0.cross(x - nd.state().p[0]);
    const Vec3 v_tissue = G * x + Vec3(0.01, -0.02, 0.03);
    const Vec3 want = c.frame.transpose() * (v_needle - v_tissue);
    // Hermite interpolation of a rigid motion is exact up to the cubic's reproduction of
    // the straight element: round-off.
    EXPECT_LT((u.segment<3>(3 * p) - want).norm(), 1e-12) << p;
  }
  // The Delassus operator is symmetric positive semi-definite.
  const Eigen::MatrixXd W = rows.delassus(tissue, needles, 1e-3);
  EXPECT_LT((W - W.transpose()).norm(), 1e-12 * W.norm());
  EXPECT_GT(Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd>(W).eigenvalues().minCoeff(), -1e-12 * W.norm());
}

// Linear-solver pieces: CHOLMOD against a dense reference, symbolic analysis reuse,
// stale-factor PCG against the direct solve, detection of a singular system.
#include <gtest/gtest.h>

#include <Eigen/Dense>

#include "needle_sim/core/error.hpp"
#include "needle_sim/solver/cholmod_solver.hpp"
#include "needle_sim/solver/gmres.hpp"
#include "needle_sim/solver/stiffness_factor.hpp"
#include "needle_sim/solver/system_solver.hpp"

using namespace needle_sim;

namespace {

struct SolverSetup {
  HexMesh mesh = HexMesh::box(Vec3(0, 0, 0), Vec3(0.04, 0.02, 0.02), Vec3i(6, 3, 3));
  LinearElasticMaterial mat{1e7, 0.4, 1000};
  CorotationalHexModel model{mesh, mat};
  DofMap dofs;
  VecX mass_free;
  SolverSetup() {
    std::vector<char> pres(mesh.numDofs(), 0);
    for (int i = 0; i < mesh.numNodes(); ++i)
      if (mesh.node(i)[0] > 0.04 - 1e-9) pres[3 * i] = pres[3 * i + 1] = pres[3 * i + 2] = 1;
    dofs = DofMap(pres);
    VecX m(mesh.numDofs());
    for (int i = 0; i < mesh.numNodes(); ++i) m.segment<3>(3 * i).setConstant(1000 * model.nodalVolume()[i]);
    dofs.gather(m, mass_free);
  }
  Eigen::MatrixXd dense(double cm, double ck) const {
    const int n = dofs.numFree();
    Eigen::MatrixXd A = Eigen::MatrixXd::Zero(n, n);
    hex8::Mat24 Ke;
    for (int e = 0; e < mesh.numElements(); ++e) {
      model.elementStiffness(e, Ke);
      const auto& el = mesh.element(e);
      for (int i = 0; i < 24; ++i)
        for (int j = 0; j < 24; ++j) {
          const int r = dofs.freeIndex(3 * el[i / 3] + i % 3), c = dofs.freeIndex(3 * el[j / 3] + j % 3);
          if (r >= 0 && c >= 0) A(r, c) += ck * Ke(i, j);
        }
    }
    A.diagonal() += cm * mass_free;
    return A;
  }
};

}  // namespace

TEST(SymmetricAssembler, UpperTriangleMatchesDenseAssembly) {
  SolverSetup s;
  SymmetricAssembler as(s.dofs.numFree(), hexElementDofs(s.mesh, s.dofs));
  hex8::Mat24 Ke;
  for (int e = 0; e < s.mesh.numElements(); ++e) {
    s.model.elementStiffness(e, Ke);
    as.addElement(e, Ke.data(), 0.5);
  }
  as.addDiagonal(s.mass_free, 3.0);
  const Eigen::MatrixXd ref = s.dense(3.0, 0.5);
  const Eigen::MatrixXd up = Eigen::MatrixXd(as.matrix());
  const Eigen::MatrixXd refUp = ref.triangularView<Eigen::Upper>();
  EXPECT_LT((up - refUp).norm(), 1e-12 * ref.norm());
}

class CholmodOrdering : public ::testing::TestWithParam<Ordering> {};

TEST_P(CholmodOrdering, SolvesAgainstDenseReferenceAndReusesAnalysis) {
  SolverSetup s;
  SymmetricAssembler as(s.dofs.numFree(), hexElementDofs(s.mesh, s.dofs));
  CholmodSolver chol(GetParam());
  hex8::Mat24 Ke;
  for (double ck : {1.0, 2.0, 0.5}) {
    as.setZero();
    for (int e = 0; e < s.mesh.numElements(); ++e) {
      s.model.elementStiffness(e, Ke);
      as.addElement(e, Ke.data(), ck);
    }
    as.addDiagonal(s.mass_free, 1.0);
    if (!chol.analyzed()) chol.analyze(as.matrix());
    ASSERT_TRUE(chol.factorize(as.matrix()));
    const VecX b = VecX::LinSpaced(s.dofs.numFree(), -1, 2);
    VecX x;
    chol.solve(b, x);
    const VecX ref = s.dense(1.0, ck).ldlt().solve(b);
    EXPECT_LT((x - ref).norm(), 1e-10 * ref.norm());
  }
  EXPECT_EQ(chol.analyses(), 1);
  EXPECT_EQ(chol.factorizations(), 3);
}

INSTANTIATE_TEST_SUITE_P(Orderings, CholmodOrdering, ::testing::Values(Ordering::Auto, Ordering::Amd, Ordering::Metis));

TEST(Cholmod, ReportsMatrixThatIsNotPositiveDefinite) {
  HexMesh mesh = HexMesh::box(Vec3(0, 0, 0), Vec3(1, 1, 1), Vec3i(2, 2, 2));
  CorotationalHexModel model(mesh, {1, 0.3, 1});
  DofMap dofs(std::vector<char>(mesh.numDofs(), 0));  // nothing held: K is singular
  SymmetricAssembler as(dofs.numFree(), hexElementDofs(mesh, dofs));
  hex8::Mat24 Ke;
  for (int e = 0; e < mesh.numElements(); ++e) {
    model.elementStiffness(e, Ke);
    as.addElement(e, Ke.data(), 1.0);
  }
  as.addDiagonal(VecX::Constant(dofs.numFree(), -1.0), 1.0);  // make it indefinite for sure
  CholmodSolver chol;
  EXPECT_FALSE(chol.factorize(as.matrix()));
  SystemSolver solver(model, dofs, LinearSolverSettings{});
  VecX x;
  EXPECT_THROW(solver.solve(VecX::Ones(dofs.numFree()), 0.0, 1.0, VecX::Ones(dofs.numFree()), x), NumericalError);
}

TEST(SystemSolver, StaleFactorPcgMatchesDirectSolve) {
  SolverSetup s;
  LinearSolverSettings pcg;
  pcg.method = LinearSolverSettings::Method::Pcg;
  pcg.tolerance = 1e-12;
  pcg.refresh_iterations = 1000;  // never refresh on iteration count: keep the factor stale
  SystemSolver solver(s.model, s.dofs, pcg);
  const double cm = 1.0, ck = 1e-6;
  const VecX b = VecX::LinSpaced(s.dofs.numFree(), -1, 1);
  VecX x0 = VecX::Zero(b.size());
  auto st0 = solver.solve(s.mass_free, cm, ck, b, x0);
  EXPECT_TRUE(st0.refactored);
  // Rotate the elements (a large deformation): A changes, the factor is now stale.
  VecX x = s.mesh.restPositions();
  for (int i = 0; i < s.mesh.numNodes(); ++i) {
    const Vec3 p = s.mesh.node(i);
    const double th = 8.0 * p[0];  // bending-like rotation, up to 0.32 rad
    x.segment<3>(3 * i) = Vec3(p[0], p[1] * std::cos(th) - p[2] * std::sin(th), p[1] * std::sin(th) + p[2] * std::cos(th));
  }
  s.model.updateRotations(x);
  VecX xs = VecX::Zero(b.size());
  const auto st = solver.solve(s.mass_free, cm, ck, b, xs);
  EXPECT_FALSE(st.refactored);
  EXPECT_GT(st.iterations, 1);
  const VecX ref = s.dense(cm, ck).ldlt().solve(b);
  EXPECT_LT((xs - ref).norm(), 1e-10 * ref.norm());
}

// Refreshing on the calling thread (static Newton), CG on a stale factor stops once it has
// cost about a factorisation (SystemSolver::staleBudget), refactorises and solves on; the
// factor it made is then not refreshed again for the next call with the same matrix (it
// was, before 2026-12-03: a factorisation per Newton iteration in the brain-shift pre-step).
TEST(SystemSolver, SynchronousRefreshStopsCgAtTheCostOfAFactorisation) {
  const double cm = 0.0, ck = 1.0;  // a static Newton system
  auto rotated = [](SolverSetup& s) {
    VecX x = s.mesh.restPositions();
    for (int i = 0; i < s.mesh.numNodes(); ++i) {
      const Vec3 p = s.mesh.node(i);
      const double th = 40.0 * (0.04 - p[0]);  // up to 1.6 rad, zero at the clamped end
      x.segment<3>(3 * i) = Vec3(p[0], p[1] * std::cos(th) - p[2] * std::sin(th), p[1] * std::sin(th) + p[2] * std::cos(th));
    }
    s.model.updateRotations(x);
  };
  LinearSolverSettings set;
  set.tolerance = 1e-10;
  set.refresh_iterations = 2;
  set.max_iterations = 500;
  set.async = false;
  SolverSetup s;
  const VecX b = VecX::LinSpaced(s.dofs.numFree(), -1, 1);
  const VecX b2 = VecX::LinSpaced(s.dofs.numFree(), 2, -1);

  // Without a budget (background refreshes: CG goes on with the stale factor) it takes many
  // iterations: the comparison below can fail.
  int unbounded = 0;
  {
    SolverSetup u;
    LinearSolverSettings a = set;
    a.async = true;
    SystemSolver solver(u.model, u.dofs, a);
    VecX x;
    EXPECT_TRUE(solver.solve(u.mass_free, cm, ck, b, x).refactored);
    rotated(u);
    x.setZero(b.size());
    const auto st = solver.solve(u.mass_free, cm, ck, b, x);
    EXPECT_FALSE(st.refactored);
    unbounded = st.iterations;
  }

  SystemSolver solver(s.model, s.dofs, set);
  VecX x;
  EXPECT_TRUE(solver.solve(s.mass_free, cm, ck, b, x).refactored);
  const CholmodSolver& f = solver.factor();
  const int budget = std::max(set.refresh_iterations + 1,
                              static_cast<int>(std::ceil(f.factorFlops() / (4.0 * f.factorNonzeros()) / 10.0)));
  ASSERT_GT(unbounded, budget + 3) << "the rotation does not make the factor stale enough for this test";
  rotated(s);
  x.setZero(b.size());
  const auto st = solver.solve(s.mass_free, cm, ck, b, x);
  EXPECT_TRUE(st.refactored);
  EXPECT_TRUE(st.budget_exhausted);
  EXPECT_LE(st.iterations, budget + 3);  // the budget on the stale factor, then a few on the new one
  const Eigen::MatrixXd A = s.dense(cm, ck);
  EXPECT_LT((x - A.ldlt().solve(b)).norm(), 1e-8 * x.norm());
  // The same matrix again: the factor just made serves it.
  VecX x2;
  const auto st2 = solver.solve(s.mass_free, cm, ck, b2, x2);
  EXPECT_FALSE(st2.refactored);
  EXPECT_LE(st2.iterations, 2);
  EXPECT_LT((x2 - A.ldlt().solve(b2)).norm(), 1e-8 * x2.norm());
}

// The duals of a goal-oriented estimate (StiffnessFactor): K at the element rotations of the
// positions given, solved directly, the step solver's factor untouched. Known answers: at rest,
// the dense K's solution; for the body turned rigidly by Q (the pinned face with it), the
// loads turned by Q give the displacements turned by Q (K(Q x) = Q K(x) Q^T, the pinned DOFs'
// components all pinned); and the extra blocks add to K. Before 2026-12-08 the duals ran CG on
// the step's factor, of c_m M + c_k K: 34 iterations a column on dbs_goal (97 ms a pass).
TEST(StiffnessFactor, SolvesTheStiffnessAtThePositionsRotations) {
  SolverSetup s;
  LinearSolverSettings set;
  SystemSolver solver(s.model, s.dofs, set);
  const int n = s.dofs.numFree();
  VecX y;
  ASSERT_TRUE(solver.solve(s.mass_free, 1.0, 1e-7, VecX::Ones(n), y).refactored);
  const long f0 = solver.factor().factorizations();
  const int nd = s.mesh.numDofs();
  Eigen::MatrixXd G(nd, 3);
  for (int k = 0; k < 3; ++k) G.col(k) = VecX::LinSpaced(nd, -1.0 + k, 1.0 - 0.5 * k);
  for (int d = 0; d < nd; ++d)
    if (s.dofs.freeIndex(d) < 0) G.row(d).setZero();  // (loads on pinned DOFs do nothing)
  StiffnessFactor factor(s.model, s.dofs, solver.assembler(), set.ordering);
  const VecX rest = s.mesh.restPositions();
  const std::vector<Eigen::Quaterniond> guesses(s.mesh.numElements(), Eigen::Quaterniond::Identity());
  ASSERT_TRUE(factor.factorAt(rest, guesses, ElementBlocks{}));
  Eigen::MatrixXd Z;
  ASSERT_TRUE(factor.solve(G, Z));
  Eigen::MatrixXd Gf(n, 3), Zf(n, 3);
  VecX c;
  for (int k = 0; k < 3; ++k) {
    s.dofs.gather(G.col(k), c);
    Gf.col(k) = c;
    s.dofs.gather(Z.col(k), c);
    Zf.col(k) = c;
  }
  const Eigen::MatrixXd K = s.dense(0.0, 1.0);
  EXPECT_LT((Zf - K.ldlt().solve(Gf)).norm(), 1e-9 * Zf.norm());
  EXPECT_EQ(solver.factor().factorizations(), f0) << "the step's factor is not the duals'";
  for (int d = 0; d < nd; ++d)
    if (s.dofs.freeIndex(d) < 0) EXPECT_EQ(Z.row(d).norm(), 0.0);

  // Turned rigidly by Q about the origin.
  const Mat3 Q = Eigen::AngleAxisd(0.7, Vec3(1, 2, -0.5).normalized()).toRotationMatrix();
  VecX xq(nd);
  Eigen::MatrixXd Gq(nd, 3), Zq;
  for (int i = 0; i < s.mesh.numNodes(); ++i) {
    xq.segment<3>(3 * i) = Q * rest.segment<3>(3 * i);
    for (int k = 0; k < 3; ++k) Gq.block<3, 1>(3 * i, k) = Q * G.block<3, 1>(3 * i, k);
  }
  ASSERT_TRUE(factor.factorAt(xq, guesses, ElementBlocks{}));
  ASSERT_TRUE(factor.solve(Gq, Zq));
  double worst = 0;
  for (int i = 0; i < s.mesh.numNodes(); ++i)
    for (int k = 0; k < 3; ++k)
      worst = std::max(worst, (Zq.block<3, 1>(3 * i, k) - Q * Z.block<3, 1>(3 * i, k)).norm());
  EXPECT_LT(worst, 1e-9 * Z.cwiseAbs().maxCoeff()) << "the factor must be of K at the positions' rotations";

  // Extra blocks (support springs) add to K: a spring on every node of element 0.
  ElementBlocks extra;
  extra.element.push_back(0);
  extra.K.push_back(1e5 * hex8::Mat24::Identity());
  ASSERT_TRUE(factor.factorAt(rest, guesses, extra));
  Eigen::MatrixXd Ze;
  ASSERT_TRUE(factor.solve(G, Ze));
  Eigen::MatrixXd Ke = K;
  const auto& el = s.mesh.element(0);
  for (int i = 0; i < 24; ++i) {
    const int r = s.dofs.freeIndex(3 * el[i / 3] + i % 3);
    if (r >= 0) Ke(r, r) += 1e5;
  }
  for (int k = 0; k < 3; ++k) {
    s.dofs.gather(Ze.col(k), c);
    Zf.col(k) = c;
  }
  EXPECT_LT((Zf - Ke.ldlt().solve(Gf)).norm(), 1e-9 * Zf.norm());
  EXPECT_GT((Zf - K.ldlt().solve(Gf)).norm(), 1e-3 * Zf.norm());
}

// A background refresh asked for compliance columns (the constraint solve's cached columns of
// A^-1) computes them with its new factor: after the swap they are the new factor's columns,
// tagged with its version, handed over once.
TEST(SystemSolver, BackgroundRefreshComputesTheAskedColumnsWithItsFactor) {
  const double cm = 1.0, ck = 1e-6;  // a dynamic step's matrix
  LinearSolverSettings set;
  set.tolerance = 1e-10;
  set.refresh_iterations = 0;  // any iteration marks the factor stale
  set.async = true;
  SolverSetup s;
  SystemSolver solver(s.model, s.dofs, set);
  const VecX b = VecX::LinSpaced(s.dofs.numFree(), -1, 1);
  VecX x;
  EXPECT_TRUE(solver.solve(s.mass_free, cm, ck, b, x).refactored);
  VecX xr = s.mesh.restPositions();
  for (int i = 0; i < s.mesh.numNodes(); ++i) {
    const Vec3 p = s.mesh.node(i);
    const double th = 10.0 * (0.04 - p[0]);
    xr.segment<3>(3 * i) = Vec3(p[0], p[1] * std::cos(th) - p[2] * std::sin(th), p[1] * std::sin(th) + p[2] * std::cos(th));
  }
  s.model.updateRotations(xr);
  const std::vector<int> asked = {0, 5, 17};
  int lambda_calls = 0;
  auto dofs = [&] {
    ++lambda_calls;
    return asked;
  };
  bool started = false, swapped = false;
  for (int k = 0; k < 20 && !swapped; ++k) {
    x.setZero(b.size());
    const auto st = solver.solve(s.mass_free, cm, ck, b, x, 0, dofs);
    started = started || st.async_started;
    swapped = st.async_swapped;
  }
  ASSERT_TRUE(started);
  ASSERT_TRUE(swapped);
  EXPECT_EQ(lambda_calls, 1) << "the DOFs are asked for only when a refresh starts";
  std::vector<int> got;
  Eigen::MatrixXd X;
  long version = -1;
  ASSERT_TRUE(solver.takeRefreshColumns(got, X, version));
  EXPECT_EQ(got, asked);
  EXPECT_EQ(version, solver.factorVersion());
  const Eigen::MatrixXd Ainv = s.dense(cm, ck).inverse();  // the rotated matrix's inverse
  for (size_t j = 0; j < asked.size(); ++j) {
    VecX e = VecX::Zero(s.dofs.numFree()), col;
    e[asked[j]] = 1.0;
    solver.factor().solve(e, col);
    EXPECT_LT((X.col(static_cast<Eigen::Index>(j)) - col).norm(), 1e-12 * col.norm());
    EXPECT_LT((X.col(static_cast<Eigen::Index>(j)) - Ainv.col(asked[j])).norm(), 1e-8 * col.norm());
  }
  EXPECT_FALSE(solver.takeRefreshColumns(got, X, version)) << "handed over once";
}

// GMRES on a nonsymmetric system A = S + N (S SPD, N skew plus a small nonsymmetric part),
// right-preconditioned by a factor of S, as static Newton with the rotation tangent runs it:
// it must reach the asked true residual and the dense LU's solution, and with the exact
// preconditioner of A converge in one iteration.
TEST(Gmres, SolvesANonsymmetricSystemPreconditionedByItsSymmetricPart) {
  const int n = 60;
  Eigen::MatrixXd R = Eigen::MatrixXd::Random(n, n);
  const Eigen::MatrixXd S = R * R.transpose() + n * Eigen::MatrixXd::Identity(n, n);
  const Eigen::MatrixXd W = Eigen::MatrixXd::Random(n, n);
  const Eigen::MatrixXd A = S + 0.3 * (W - W.transpose()) + 0.1 * W;
  const VecX b = VecX::Random(n);
  const Eigen::LLT<Eigen::MatrixXd> llt(S);
  auto apply = [&](const VecX& v, VecX& out) { out = A * v; };
  auto precondition = [&](const VecX& r, VecX& z) { z = llt.solve(r); };
  VecX x = VecX::Zero(n);
  const PcgResult res = gmres(apply, precondition, b, x, 1e-10, 50);
  EXPECT_TRUE(res.converged);
  EXPECT_GT(res.iterations, 1);
  EXPECT_LT((b - A * x).norm(), 1e-10 * b.norm());
  EXPECT_LT(res.relative_residual, 1e-10);
  const VecX ref = A.partialPivLu().solve(b);
  EXPECT_LT((x - ref).norm(), 1e-8 * ref.norm());
  // Too few iterations: reported as not converged, with the true residual.
  VecX y = VecX::Zero(n);
  const PcgResult short_run = gmres(apply, precondition, b, y, 1e-10, 2);
  EXPECT_FALSE(short_run.converged);
  EXPECT_NEAR(short_run.relative_residual, (b - A * y).norm() / b.norm(), 1e-12);
  // Without a preconditioner it needs more than one restart cycle (kGmresRestart vectors):
  // the restarts must still converge, from the true residual.
  // A spread spectrum (a positive definite symmetric part, 1 ... 1e4, plus a skew part) needs
  // them: restarted GMRES converges when the symmetric part is positive definite (Elman).
  Eigen::MatrixXd B = 0.5 * (W - W.transpose());
  for (int i = 0; i < n; ++i) B(i, i) = std::pow(10.0, 4.0 * i / (n - 1));
  VecX u = VecX::Zero(n);
  const PcgResult plain = gmres([&](const VecX& v, VecX& out) { out = B * v; },
                                [](const VecX& r, VecX& out) { out = r; }, b, u, 1e-10, 5000);
  EXPECT_TRUE(plain.converged);
  EXPECT_GT(plain.iterations, kGmresRestart);
  EXPECT_LT((b - B * u).norm(), 1e-10 * b.norm());
  // The exact inverse as preconditioner: one iteration.
  const Eigen::PartialPivLU<Eigen::MatrixXd> lu(A);
  VecX z = VecX::Zero(n);
  const PcgResult exact = gmres(apply, [&](const VecX& r, VecX& out) { out = lu.solve(r); }, b, z, 1e-10, 50);
  EXPECT_EQ(exact.iterations, 1);
  EXPECT_TRUE(exact.converged);
}

#include "needle_sim/solver/system_solver.hpp"

#include <chrono>

#include "needle_sim/core/error.hpp"
#include "needle_sim/core/stopwatch.hpp"
#include "needle_sim/solver/pcg.hpp"

namespace needle_sim {


SystemSolver::SystemSolver(const CorotationalHexModel& model, const DofMap& dofs,
                           const LinearSolverSettings& s)
    : model_(model), dofs_(dofs), settings_(s), assembler_(dofs.numFree(), hexElementDofs(model.mesh(), dofs)), chol_(s.ordering) {}

SystemSolver::SystemSolver(const SystemSolver& o, const CorotationalHexModel& model, const DofMap& dofs)
    : model_(model),
      dofs_(dofs),
      settings_(o.settings_),
      assembler_(o.assembler_),
      chol_(o.chol_),
      stale_(o.stale_),
      calls_since_factor_(o.calls_since_factor_) {}

void SystemSolver::apply(const VecX& mass_free, double c_m, double c_k, const VecX& v, VecX& out) const {
  dofs_.scatter(v, full_in_);
  full_out_.setZero(dofs_.numFull());
  model_.addStiffnessProduct(full_in_, c_k, full_out_);
  if (extra_) {
    Eigen::Matrix<double, 24, 1> ve;
    for (size_t i = 0; i < extra_->element.size(); ++i) {
      const auto& el = model_.mesh().element(extra_->element[i]);
      for (int a = 0; a < 8; ++a) ve.segment<3>(3 * a) = node3(full_in_, el[a]);
      const Eigen::Matrix<double, 24, 1> w = extra_->K[i] * ve;
      for (int a = 0; a < 8; ++a) node3(full_out_, el[a]) += c_k * w.segment<3>(3 * a);
    }
  }
  dofs_.gather(full_out_, out);
  out.array() += c_m * mass_free.array() * v.array();
}

void SystemSolver::refactor(const VecX& mass_free, double c_m, double c_k, LinearSolveStats& st) {
  auto t0 = steadyNow();
  assembler_.setZero();
  hex8::Mat24 Ke;
  for (int e = 0; e < model_.numElements(); ++e) {
    model_.elementStiffness(e, Ke);
    assembler_.addElement(e, Ke.data(), c_k);
  }
  if (extra_)
    for (size_t i = 0; i < extra_->element.size(); ++i) assembler_.addElement(extra_->element[i], extra_->K[i].data(), c_k);
  if (c_m != 0.0) assembler_.addDiagonal(mass_free, c_m);
  st.assemble_ms += msSince(t0);
  t0 = steadyNow();
  if (!chol_.analyzed()) chol_.analyze(assembler_.matrix());
  const bool ok = chol_.factorize(assembler_.matrix());
  st.factor_ms += msSince(t0);
  st.refactored = true;
  if (!ok)
    throw NumericalError(-1, "system matrix is not positive definite (are rigid motions "
                             "constrained? is the mesh inverted?)");
  stale_ = false;
  calls_since_factor_ = 0;
}

LinearSolveStats SystemSolver::solve(const VecX& mass_free, double c_m, double c_k, const VecX& b, VecX& x,
                                     double tolerance) {
  LinearSolveStats st;
  const bool direct = settings_.method == LinearSolverSettings::Method::Direct;
  if (direct || stale_ || !chol_.factored() ||
      (settings_.refactor_every > 0 && calls_since_factor_ >= settings_.refactor_every))
    refactor(mass_free, c_m, c_k, st);
  ++calls_since_factor_;

  auto t0 = steadyNow();
  if (direct) {
    chol_.solve(b, x);
    st.solve_ms = msSince(t0);
    if (!x.allFinite()) throw NumericalError(-1, "linear solve produced NaN/Inf");
    return st;
  }
  auto A = [&](const VecX& v, VecX& out) { apply(mass_free, c_m, c_k, v, out); };
  auto M = [&](const VecX& r, VecX& z) { chol_.solve(r, z); };
  if (x.size() != b.size() || !x.allFinite()) x.setZero(b.size());
  const double tol = tolerance > 0 ? tolerance : settings_.tolerance;
  PcgResult r = pcg(A, M, b, x, tol, settings_.max_iterations);
  if (!r.converged && !st.refactored) {
    // The stale preconditioner is too far off: refresh it and solve again.
    st.solve_ms += msSince(t0);
    refactor(mass_free, c_m, c_k, st);
    t0 = steadyNow();
    const int first = r.iterations;
    r = pcg(A, M, b, x, tol, settings_.max_iterations);
    r.iterations += first;
  }
  st.solve_ms += msSince(t0);
  st.iterations = r.iterations;
  st.relative_residual = r.relative_residual;
  if (!r.converged || !x.allFinite())
    throw NumericalError(-1, "conjugate gradients did not converge (relative residual " +
                                 std::to_string(r.relative_residual) + ")");
  if (r.iterations > settings_.refresh_iterations) stale_ = true;
  return st;
}

LinearSolveStats SystemSolver::solveWithFactor(const VecX& mass_free, double c_m, double c_k, const Eigen::MatrixXd& B,
                                               Eigen::MatrixXd& X, double tolerance, int max_iterations,
                                               bool& converged) {
  LinearSolveStats st;
  const bool own_factor = !chol_.factored();  // e.g. the first estimate on a new mesh, before any step
  if (own_factor) refactor(mass_free, c_m, c_k, st);
  const auto t0 = steadyNow();
  auto A = [&](const VecX& v, VecX& out) { apply(mass_free, c_m, c_k, v, out); };
  auto M = [&](const VecX& r, VecX& z) { chol_.solve(r, z); };
  // X as it comes is the initial guess when it has B's shape (a previous pass's solution).
  if (X.rows() != B.rows() || X.cols() != B.cols() || !X.allFinite()) X.setZero(B.rows(), B.cols());
  converged = true;
  for (Eigen::Index j = 0; j < B.cols(); ++j) {
    VecX x = X.col(j);
    const PcgResult r = pcg(A, M, B.col(j), x, tolerance, max_iterations);
    X.col(j) = x;
    st.iterations = std::max(st.iterations, r.iterations);
    st.relative_residual = std::max(st.relative_residual, r.relative_residual);
    converged = converged && r.converged && x.allFinite();
  }
  st.solve_ms += msSince(t0);
  // A factor made here is of this call's matrix (the dual's K), not of the step's A: the next
  // step must refactor rather than take it as its preconditioner, and the compliance cache
  // must not take its columns (they would be K^-1's, about h(h + beta) too small).
  if (own_factor) stale_ = true;
  return st;
}

}  // namespace needle_sim

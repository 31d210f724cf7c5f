#include "needle_sim/solver/system_solver.hpp"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <chrono>
#include <thread>

#include "needle_sim/core/background_priority.hpp"
#include "needle_sim/core/error.hpp"
#include "needle_sim/core/stopwatch.hpp"
#include "needle_sim/solver/gmres.hpp"
#include "needle_sim/solver/pcg.hpp"

namespace needle_sim {

namespace {
std::atomic<double> g_refresh_delay_ms{0.0};
}  // namespace

void SystemSolver::setRefreshDelayForTesting(double ms) { g_refresh_delay_ms = ms; }

SystemSolver::SystemSolver(const CorotationalHexModel& model, const DofMap& dofs,
                           const LinearSolverSettings& s)
    : model_(model),
      dofs_(dofs),
      settings_(s),
      assembler_(dofs.numFree(), hexElementDofs(model.mesh(), dofs)),
      chol_(std::make_unique<CholmodSolver>(s.ordering)),
      async_(s.async) {}

SystemSolver::SystemSolver(const SystemSolver& o, const CorotationalHexModel& model, const DofMap& dofs)
    : model_(model),
      dofs_(dofs),
      settings_(o.settings_),
      assembler_(o.assembler_),
      chol_(std::make_unique<CholmodSolver>(*o.chol_)),
      version_(o.version_),
      stale_(o.stale_),
      must_refactor_(o.must_refactor_),
      async_(o.async_),
      hold_(o.hold_),
      calls_(o.calls_),
      calls_since_factor_(o.calls_since_factor_),
      factor_rot_(o.factor_rot_),
      swap_in_solve_(o.swap_in_solve_) {  // capture_: the copy's owner points it at its own
  if (o.pending_) {
    // The copy steps as the original will: it gets the same refresh, finished (so its own
    // swap, at the same call, needs no thread).
    const bool ok = o.pending_->done.get();
    pending_ = std::make_unique<Refresh>();
    pending_->factor = std::make_unique<CholmodSolver>(*o.pending_->factor);
    pending_->requested_call = o.pending_->requested_call;
    pending_->column_dofs = o.pending_->column_dofs;
    pending_->columns = o.pending_->columns;
    pending_->rotations = o.pending_->rotations;
    pending_->work_ms = o.pending_->work_ms;
    std::promise<bool> p;
    p.set_value(ok);
    pending_->done = p.get_future().share();
  }
}

SystemSolver::~SystemSolver() { dropRefresh(); }

bool SystemSolver::refreshRunning() const {
  return pending_ && pending_->done.valid() &&
         pending_->done.wait_for(std::chrono::seconds(0)) != std::future_status::ready;
}

void SystemSolver::dropRefresh() {
  if (pending_ && pending_->done.valid()) pending_->done.wait();  // the thread reads the model
  pending_.reset();
}

void SystemSolver::invalidate() {
  dropRefresh();
  must_refactor_ = true;
}

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
  if (nonsymmetric_) (*nonsymmetric_)(full_in_, c_k, full_out_);
  dofs_.gather(full_out_, out);
  out.array() += c_m * mass_free.array() * v.array();
}

void SystemSolver::refactor(const VecX& mass_free, double c_m, double c_k, LinearSolveStats& st) {
  dropRefresh();  // superseded: this factor is newer
  auto t0 = steadyNow();
  assembler_.setZero();
  hex8::Mat24 Ke;
  // Lagged rotations: the factor of the positions' rotations, which the model takes from the
  // next step on (this one's matrix has the model's: CG makes up the difference once).
  const bool captured = capture_ && capture_->size() == static_cast<size_t>(model_.numElements());
  for (int e = 0; e < model_.numElements(); ++e) {
    if (captured) model_.elementStiffness(e, (*capture_)[static_cast<size_t>(e)], Ke);
    else model_.elementStiffness(e, Ke);
    assembler_.addElement(e, Ke.data(), c_k);
  }
  if (extra_)
    for (size_t i = 0; i < extra_->element.size(); ++i) assembler_.addElement(extra_->element[i], extra_->K[i].data(), c_k);
  if (c_m != 0.0) assembler_.addDiagonal(mass_free, c_m);
  st.assemble_ms += msSince(t0);
  t0 = steadyNow();
  if (!chol_->analyzed()) chol_->analyze(assembler_.matrix());
  const bool ok = chol_->factorize(assembler_.matrix());
  st.factor_ms += msSince(t0);
  st.refactored = true;
  ++version_;
  factor_rot_ = captured ? *capture_ : model_.rotations();
  if (!ok)
    throw NumericalError(-1, "system matrix is not positive definite (are rigid motions "
                             "constrained? is the mesh inverted?)");
  stale_ = false;
  must_refactor_ = false;
  calls_since_factor_ = 0;
}

void SystemSolver::startRefresh(const VecX& mass_free, double c_m, double c_k, LinearSolveStats& st,
                                const std::function<std::vector<int>()>& column_dofs) {
  // On this thread only what the matrix depends on (rotations, mass, scales, extra blocks):
  // a few hundred kilobytes. The thread reads the model's element references and the
  // assembler's scatter map, which do not change while this solver lives.
  std::unique_ptr<Refresh> r = spare_ ? std::move(spare_) : std::make_unique<Refresh>();
  r->rotations.resize(model_.numElements());
  const bool captured = capture_ && capture_->size() == static_cast<size_t>(model_.numElements());
  for (int e = 0; e < model_.numElements(); ++e) r->rotations[e] = captured ? (*capture_)[e] : model_.rotation(e);
  r->mass_free = mass_free;
  r->c_m = c_m;
  r->c_k = c_k;
  r->extra = extra_ ? *extra_ : ElementBlocks{};
  r->requested_call = calls_;
  r->column_dofs = column_dofs ? column_dofs() : std::vector<int>{};
  r->columns.resize(0, 0);
  columns_version_ = -1;  // a swapped refresh's columns not taken are gone (r may be its buffers)
  Refresh* job = r.get();
  const CorotationalHexModel* model = &model_;
  const SymmetricAssembler* assembler = &assembler_;
  const CholmodSolver* in_use = chol_.get();
  r->done = std::async(std::launch::async, [job, model, assembler, in_use] {
              lowerThisThreadPriority();
              nameThisThread("ns_refactor");
              const auto t0 = steadyNow();
              // The first refresh copies the factor in use (its analysis; the values are
              // overwritten) and the matrix's pattern here: on the stepping thread the copy
              // cost 20-30 ms on the DBS mesh. Both are only read meanwhile: the stepping
              // thread changes them in refactor() alone, which first waits for this job.
              if (!job->factor) {
                job->factor = std::make_unique<CholmodSolver>(*in_use);
                job->matrix = assembler->matrix();
              }
              double* v = job->matrix.valuePtr();
              std::fill(v, v + job->matrix.nonZeros(), 0.0);
              hex8::Mat24 Ke;
              for (int e = 0; e < model->numElements(); ++e) {
                model->elementStiffness(e, job->rotations[e], Ke);
                assembler->addElementTo(v, e, Ke.data(), job->c_k);
              }
              for (size_t i = 0; i < job->extra.element.size(); ++i)
                assembler->addElementTo(v, job->extra.element[i], job->extra.K[i].data(), job->c_k);
              if (job->c_m != 0.0) assembler->addDiagonalTo(v, job->mass_free, job->c_m);
              const bool ok = job->factor->factorize(job->matrix);
              if (ok && !job->column_dofs.empty()) {
                const auto n = static_cast<Eigen::Index>(job->matrix.rows());
                Eigen::MatrixXd E = Eigen::MatrixXd::Zero(n, static_cast<Eigen::Index>(job->column_dofs.size()));
                for (size_t j = 0; j < job->column_dofs.size(); ++j) E(job->column_dofs[j], static_cast<Eigen::Index>(j)) = 1.0;
                job->factor->solve(E, job->columns);
              }
              const double delay = g_refresh_delay_ms;
              if (delay > 0) std::this_thread::sleep_for(std::chrono::duration<double, std::milli>(delay));
              job->work_ms = msSince(t0);
              return ok;
            }).share();
  pending_ = std::move(r);
  st.async_started = true;
}

bool SystemSolver::finishRefresh(LinearSolveStats& st) {
  Refresh& r = *pending_;
  if (r.done.wait_for(std::chrono::seconds(0)) != std::future_status::ready) {
    const auto t0 = steadyNow();
    r.done.wait();
    st.async_wait_ms += msSince(t0);
    st.async_waited = true;
  }
  const bool ok = r.done.get();
  if (ok) {
    std::swap(chol_, r.factor);  // the old factor's buffers serve the next refresh
    factor_rot_ = r.rotations;
    ++version_;
      columns_version_ = r.columns.size() > 0 ? version_ : -1;
    stale_ = false;
    calls_since_factor_ = calls_ - r.requested_call;
    st.async_swapped = true;
  }
  spare_ = std::move(pending_);
  return ok;
}

bool SystemSolver::swapDueRefresh(LinearSolveStats& st, long ahead) {
  if (!pending_) return false;
  // Swapped in at a fixed number of calls after the request (the same results whatever the
  // thread's timing), or as soon as it is ready with async_lag 0.
  const bool due = settings_.async_lag > 0
                       ? calls_ + ahead - pending_->requested_call >= settings_.async_lag
                       : pending_->done.wait_for(std::chrono::seconds(0)) == std::future_status::ready;
  if (due && !finishRefresh(st)) stale_ = true;
  return st.async_swapped;
}

LinearSolveStats SystemSolver::solve(const VecX& mass_free, double c_m, double c_k, const VecX& b, VecX& x,
                                     double tolerance, const std::function<std::vector<int>()>& column_dofs) {
  LinearSolveStats st;
  ++calls_;
  const bool direct = settings_.method == LinearSolverSettings::Method::Direct;
  if (swap_in_solve_) swapDueRefresh(st, 0);
  if (direct || must_refactor_ || !chol_->factored() ||
      (settings_.refactor_every > 0 && calls_since_factor_ >= settings_.refactor_every)) {
    refactor(mass_free, c_m, c_k, st);
  } else if (stale_ && !pending_ && !hold_) {
    if (async_) startRefresh(mass_free, c_m, c_k, st, column_dofs);
    else refactor(mass_free, c_m, c_k, st);
  }
  ++calls_since_factor_;

  auto t0 = steadyNow();
  if (direct) {
    chol_->solve(b, x);
    st.solve_ms = msSince(t0);
    if (!x.allFinite()) throw NumericalError(-1, "linear solve produced NaN/Inf");
    return st;
  }
  auto A = [&](const VecX& v, VecX& out) { apply(mass_free, c_m, c_k, v, out); };
  auto M = [&](const VecX& r, VecX& z) { chol_->solve(r, z); };
  if (x.size() != b.size() || !x.allFinite()) x.setZero(b.size());
  const double tol = tolerance > 0 ? tolerance : settings_.tolerance;
  auto krylov = [&](int max_iterations) {
    return nonsymmetric_ ? gmres(A, M, b, x, tol, max_iterations) : pcg(A, M, b, x, tol, max_iterations);
  };
  PcgResult r = krylov(st.refactored ? settings_.max_iterations : staleBudget());
  int on_last_factor = r.iterations;  // CG iterations with the factor this call ends with
  // The preconditioner is too far off: take the pending refresh (waiting for it) and solve
  // again; if that is not enough either (it was made for an older matrix), refresh now.
  for (int attempt = 0; attempt < 2 && !r.converged && !st.refactored; ++attempt) {
    st.solve_ms += msSince(t0);
    if (!(attempt == 0 && pending_ && finishRefresh(st))) {
      refactor(mass_free, c_m, c_k, st);
      st.budget_exhausted = true;
    }
    t0 = steadyNow();
    const int first = r.iterations;
    r = krylov(settings_.max_iterations);
    on_last_factor = r.iterations;
    r.iterations += first;
  }
  st.solve_ms += msSince(t0) + st.async_wait_ms;
  st.iterations = r.iterations;
  st.relative_residual = r.relative_residual;
  if (!r.converged || !x.allFinite())
    throw NumericalError(-1, std::string(nonsymmetric_ ? "GMRES" : "conjugate gradients") + " did not converge (relative residual " +
                                 std::to_string(r.relative_residual) + ")");
  // Judged on the factor now in use: one just made for this matrix is not stale, however
  // many iterations the old one took first (a second refactorisation at the next call, for
  // nearly the same matrix, cost static Newton a factorisation per iteration).
  // With a nonsymmetric term the factor (of the symmetric part) is never exact: GMRES takes
  // several iterations with a fresh one, so staleness counts the iterations beyond those the
  // first solve with the factor needed.
  if (st.refactored) fresh_iterations_ = nonsymmetric_ ? on_last_factor : 0;
  const int expected = nonsymmetric_ ? fresh_iterations_ : 0;
  if (on_last_factor > settings_.refresh_iterations + expected && !pending_) stale_ = true;
  return st;
}

int SystemSolver::staleBudget() const {
  if (async_) return settings_.max_iterations;
  // Refreshing on this thread: CG on a stale factor goes on only while its iterations cost
  // less than a refactorisation (then it refactors and solves again from where it got: never
  // more than twice the cost of refactorising at once, and nothing lost when CG is
  // nearly done). Costs from the factor's flop count and nonzeros (deterministic: the
  // same scene and settings take the same path): one iteration is two triangular solves,
  // about 4 nnz(L) flops, which run memory-bound at about a tenth of the factorisation's
  // dense-kernel rate (measured: 5-14x on the DBS meshes, 2026-12-03).
  constexpr double kFactorToSolveRate = 10.0;
  const double lnz = chol_->factorNonzeros();
  const double iterations = lnz > 0 ? chol_->factorFlops() / (4.0 * lnz) / kFactorToSolveRate : 0.0;
  return std::clamp(static_cast<int>(std::ceil(iterations)), settings_.refresh_iterations + 1, settings_.max_iterations);
}

bool SystemSolver::takeRefreshColumns(std::vector<int>& dofs, Eigen::MatrixXd& X, long& version) {
  if (columns_version_ < 0 || !spare_) return false;
  dofs = std::move(spare_->column_dofs);
  X = std::move(spare_->columns);
  spare_->column_dofs.clear();
  spare_->columns.resize(0, 0);
  version = columns_version_;
  columns_version_ = -1;
  return true;
}

}  // namespace needle_sim

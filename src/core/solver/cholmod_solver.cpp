#include "needle_sim/solver/cholmod_solver.hpp"

#include <cholmod.h>

#include <cassert>
#include <mutex>
#include <stdexcept>

namespace needle_sim {

namespace {

cholmod_sparse viewUpper(const SparseMatrix& A) {
  assert(A.isCompressed());
  cholmod_sparse s{};
  s.nrow = static_cast<size_t>(A.rows());
  s.ncol = static_cast<size_t>(A.cols());
  s.nzmax = static_cast<size_t>(A.nonZeros());
  s.p = const_cast<int*>(A.outerIndexPtr());
  s.i = const_cast<int*>(A.innerIndexPtr());
  s.nz = nullptr;
  s.x = const_cast<double*>(A.valuePtr());
  s.z = nullptr;
  s.stype = 1;  // symmetric, upper triangle stored
  s.itype = CHOLMOD_INT;
  s.xtype = CHOLMOD_REAL;
  s.dtype = CHOLMOD_DOUBLE;
  s.sorted = 1;
  s.packed = 1;
  return s;
}

// METIS keeps its random generator's state in globals (GKlib) and reseeds it at each call:
// orderings made on two threads at once interleave their draws and differ from run to run.
// One analysis that may order with METIS (metis, or auto falling back to it) at a time keeps
// every ordering reproducible.
std::mutex& analysisMutex() {
  static std::mutex m;
  return m;
}

}  // namespace

CholmodSolver::CholmodSolver(Ordering ordering) : ordering_(ordering) {
  common_ = new cholmod_common;
  cholmod_start(common_);
  common_->print = 0;  // errors are reported through return values, not stdout
  common_->error_handler = nullptr;
  common_->supernodal = CHOLMOD_AUTO;  // simplicial for tiny systems, supernodal otherwise
  // LL^T also in simplicial mode: an LDL^T factorisation would accept an indefinite matrix
  // silently, and positive definiteness is what we check.
  common_->final_ll = 1;
  switch (ordering) {
    case Ordering::Auto:
      // CHOLMOD's default: AMD, then METIS if AMD's fill is poor. (METIS gives the DBS mesh
      // a 19 % smaller factor, 627 k nonzeros against 774 k, but the DBS steps only 5-10 %
      // faster: doc/benchmarks.md, "Bounded step time".)
      break;
    case Ordering::Amd:
      common_->nmethods = 1;
      common_->method[0].ordering = CHOLMOD_AMD;
      common_->postorder = 1;
      break;
    case Ordering::Metis:
      common_->nmethods = 1;
      common_->method[0].ordering = CHOLMOD_METIS;
      common_->postorder = 1;
      break;
  }
}

CholmodSolver::CholmodSolver(const CholmodSolver& o) : CholmodSolver(o.ordering_) {
  if (o.factor_) {
    factor_ = cholmod_copy_factor(o.factor_, common_);
    if (!factor_) throw std::runtime_error("CHOLMOD could not copy a factor (status " + std::to_string(common_->status) + ")");
  }
  n_ = o.n_;
  lnz_ = o.lnz_;
  flops_ = o.flops_;
  factored_ = o.factored_;
  analyses_ = o.analyses_;
  factorizations_ = o.factorizations_;
}

CholmodSolver::~CholmodSolver() {
  if (factor_) cholmod_free_factor(&factor_, common_);
  if (x_) cholmod_free_dense(&x_, common_);
  if (y_) cholmod_free_dense(&y_, common_);
  if (e_) cholmod_free_dense(&e_, common_);
  cholmod_finish(common_);
  delete common_;
}

void CholmodSolver::analyze(const SparseMatrix& upper) {
  if (factor_) cholmod_free_factor(&factor_, common_);
  factored_ = false;
  cholmod_sparse A = viewUpper(upper);
  std::unique_lock<std::mutex> lock(analysisMutex(), std::defer_lock);
  if (ordering_ != Ordering::Amd) lock.lock();  // AMD keeps no global state: no need to wait
  factor_ = cholmod_analyze(&A, common_);
  if (lock.owns_lock()) lock.unlock();
  if (!factor_) throw std::runtime_error("CHOLMOD analysis failed (status " + std::to_string(common_->status) + ")");
  n_ = static_cast<int>(upper.rows());
  // The analysis's counts for the chosen ordering (kept: a copy's common has none).
  lnz_ = common_->lnz;
  flops_ = common_->fl;
  ++analyses_;
}

bool CholmodSolver::factorize(const SparseMatrix& upper) {
  if (!factor_ || upper.rows() != n_) analyze(upper);
  cholmod_sparse A = viewUpper(upper);
  const int ok = cholmod_factorize(&A, factor_, common_);
  ++factorizations_;
  factored_ = ok && common_->status == CHOLMOD_OK && factor_->minor == factor_->n;
  return factored_;
}

void CholmodSolver::solve(const VecX& b, VecX& x) const {
  if (!factored_) throw std::logic_error("CholmodSolver::solve without a valid factor");
  assert(b.size() == n_);
  cholmod_dense B{};
  B.nrow = static_cast<size_t>(n_);
  B.ncol = 1;
  B.nzmax = static_cast<size_t>(n_);
  B.d = static_cast<size_t>(n_);
  B.x = const_cast<double*>(b.data());
  B.z = nullptr;
  B.xtype = CHOLMOD_REAL;
  B.dtype = CHOLMOD_DOUBLE;
  if (!cholmod_solve2(CHOLMOD_A, factor_, &B, nullptr, &x_, nullptr, &y_, &e_, common_))
    throw std::runtime_error("CHOLMOD solve failed");
  x = Eigen::Map<const VecX>(static_cast<const double*>(x_->x), n_);
}

void CholmodSolver::solve(const Eigen::MatrixXd& Bm, Eigen::MatrixXd& X) const {
  if (!factored_) throw std::logic_error("CholmodSolver::solve without a valid factor");
  assert(Bm.rows() == n_);
  cholmod_dense B{};
  B.nrow = static_cast<size_t>(n_);
  B.ncol = static_cast<size_t>(Bm.cols());
  B.nzmax = B.nrow * B.ncol;
  B.d = static_cast<size_t>(n_);
  B.x = const_cast<double*>(Bm.data());
  B.z = nullptr;
  B.xtype = CHOLMOD_REAL;
  B.dtype = CHOLMOD_DOUBLE;
  // Workspaces of this call only: with the single-column solves' (y_, e_), the result's last
  // bits depended on what the solver had solved before, and a copy of a simulation whose
  // background refresh computes compliance columns (SystemSolver) drifted from the original.
  cholmod_dense *Xd = nullptr, *Y = nullptr, *E = nullptr;
  const int ok = cholmod_solve2(CHOLMOD_A, factor_, &B, nullptr, &Xd, nullptr, &Y, &E, common_);
  if (Y) cholmod_free_dense(&Y, common_);
  if (E) cholmod_free_dense(&E, common_);
  if (!ok) {
    if (Xd) cholmod_free_dense(&Xd, common_);
    throw std::runtime_error("CHOLMOD solve failed");
  }
  X = Eigen::Map<const Eigen::MatrixXd>(static_cast<const double*>(Xd->x), n_, Bm.cols());
  cholmod_free_dense(&Xd, common_);
}

double CholmodSolver::factorNonzeros() const { return lnz_; }
double CholmodSolver::factorFlops() const { return flops_; }
bool CholmodSolver::supernodal() const { return factor_ && factor_->is_super; }
std::string CholmodSolver::orderingName() const {
  if (!factor_) return "none";
  switch (factor_->ordering) {
    case CHOLMOD_NATURAL: return "natural";
    case CHOLMOD_AMD: return "amd";
    case CHOLMOD_METIS: return "metis";
    case CHOLMOD_NESDIS: return "nesdis";
    case CHOLMOD_COLAMD: return "colamd";
    default: return "other";
  }
}

}  // namespace needle_sim

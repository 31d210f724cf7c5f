#pragma once
// Solves the linear systems of one deformable body,
//     A dx = b,   A = c_m diag(m) + c_k K(x)      (over the free DOFs),
// which covers the implicit Euler step (c_m = 1 + h alpha, c_k = h beta + h^2) and the
// Newton step of static equilibrium (c_m = 0, c_k = 1).
//
// Two methods:
//  - direct: assemble A, refactorise it with CHOLMOD and solve, every call;
//  - pcg: conjugate gradients on the exact, matrix-free A, preconditioned by a CHOLMOD
//    factor of an earlier A. The corotational A changes only through the element rotations,
//    so a factor a few steps old is a near-exact preconditioner (Courtecuisse et al.); it is
//    refreshed when CG needs more than `refresh_iterations`, every `refactor_every` calls if
//    set, or when CG fails (refreshing on the calling thread: when CG has run as many
//    iterations as a factorisation costs, staleBudget()). The answer satisfies the same tolerance either way.
//
// The refresh is asynchronous by default (`async`, doc/method.md "Time integration"): the
// element rotations of the call that asks for it are captured, and a background thread
// assembles and factorises that matrix into a second factor (its own CHOLMOD workspace)
// while the calls go on with the old one, as many CG iterations as they need (up to
// `max_iterations`). The new factor is swapped in at the start of the call `async_lag` calls
// after the request, waiting for it if it is late; with `async_lag` 0 as soon as it is
// ready. A fixed lag makes the results independent of thread timing (the same scene and
// settings give the same numbers, bit for bit); "as soon as ready" never waits, and its
// results differ from run to run within the CG tolerance. A call whose CG does not converge
// with the old factor waits for the pending one (counted), or refactorises at once if none
// is pending.
#include <future>
#include <memory>
#include <vector>

#include <Eigen/StdVector>

#include "needle_sim/core/types.hpp"
#include "needle_sim/fem/corotational_hex_model.hpp"
#include <functional>
#include <vector>

#include "needle_sim/solver/cholmod_solver.hpp"
#include "needle_sim/solver/dof_map.hpp"
#include "needle_sim/solver/symmetric_assembler.hpp"

namespace needle_sim {

struct LinearSolverSettings {
  enum class Method { Direct, Pcg };
  Method method = Method::Pcg;
  double tolerance = 1e-8;     // relative residual of CG
  int max_iterations = 50;     // CG iterations before falling back to a fresh factor
  int refresh_iterations = 8;  // refactor for the next call when CG needed more than this
  int refactor_every = 0;      // also refactor every N calls (0: only on demand)
  Ordering ordering = Ordering::Auto;
  bool async = true;           // refresh the factor on a background thread
  int async_lag = 4;           // swap it in this many calls after the request (0: when ready)
  double rotation_drift = 0;   // lagged rotations (TissueBody::freeMotion): refresh past this angle [rad]; 0: off
  bool columns_ahead = false;  // a refresh also computes the columns ahead of the needles (TissueBody::setElementsAhead)
};

// Extra symmetric stiffness given per element as 24x24 blocks over the element's nodes
// (e.g. the skull-contact penalty of the brain-shift pre-step); it keeps the sparsity pattern.
struct ElementBlocks {
  std::vector<int> element;
  std::vector<hex8::Mat24, Eigen::aligned_allocator<hex8::Mat24>> K;
  void clear() {
    element.clear();
    K.clear();
  }
};

struct LinearSolveStats {
  int iterations = 0;           // CG iterations (0 for a direct solve)
  double relative_residual = 0;
  bool refactored = false;      // a factorisation on this call's thread
  bool budget_exhausted = false;  // ... because CG on the stale factor ran out of its budget
  double assemble_ms = 0, factor_ms = 0, solve_ms = 0;
  bool async_started = false;   // a background refresh was requested
  bool async_swapped = false;   // a background factor was swapped in
  bool async_waited = false;    // ... after waiting for it
  double async_wait_ms = 0;     // time spent waiting
};

class SystemSolver {
 public:
  SystemSolver(const CorotationalHexModel& model, const DofMap& dofs, const LinearSolverSettings& s);
  // A copy (factor included) for `model` and `dofs`, copies of other's; the extra stiffness
  // is not carried over (the owner sets its own copy).
  SystemSolver(const SystemSolver& other, const CorotationalHexModel& model, const DofMap& dofs);
  SystemSolver(const SystemSolver&) = delete;
  SystemSolver& operator=(const SystemSolver&) = delete;

  // Solves with the model's current rotations; x holds the initial guess on entry.
  // mass_free is the lumped mass over the free DOFs. Throws NumericalError(-1, ...) when
  // the matrix is not positive definite or the solve fails. tolerance > 0 replaces the
  // settings' CG tolerance for this call (an inexact Newton step); ignored by the direct method.
  // column_dofs, when given, names the free DOFs whose columns of A^-1 a background refresh
  // started by this call also computes with its new factor (the constraint solve's cached
  // compliance columns: refreshed with the factor instead of on the stepping thread; called
  // only when a refresh starts); takeRefreshColumns hands them over after the swap.
  LinearSolveStats solve(const VecX& mass_free, double c_m, double c_k, const VecX& b, VecX& x, double tolerance = 0,
                         const std::function<std::vector<int>()>& column_dofs = {});
  // After a call that swapped in a background refresh (async_swapped): the columns it
  // computed (dofs, one column of X each) and the factor version they belong to; false when
  // there are none (none asked for, or already taken).
  bool takeRefreshColumns(std::vector<int>& dofs, Eigen::MatrixXd& X, long& version);
  // out = A v over the free DOFs, matrix-free.
  void apply(const VecX& mass_free, double c_m, double c_k, const VecX& v, VecX& out) const;
  // Adds c_k * blocks to A until cleared (nullptr); the caller keeps them alive and
  // invalidates the factor when they change.
  void setExtraStiffness(const ElementBlocks* blocks) { extra_ = blocks; }
  // A term(v_full, c_k, out_full) adding c_k * N v to A v until cleared (nullptr), N not
  // symmetric and not in the factor (the rotation part of the static tangent, kept alive by
  // the caller): solve() then runs GMRES, preconditioned by the factor, instead of CG.
  using OperatorTerm = std::function<void(const VecX&, double, VecX&)>;
  void setNonsymmetricTerm(const OperatorTerm* term) { nonsymmetric_ = term; }
  // Factorises A = c_m M + c_k K at the model's current rotations now (a body built off the
  // stepping thread for a deferred mesh change gets its first factor there).
  LinearSolveStats factorNow(const VecX& mass_free, double c_m, double c_k) {
    LinearSolveStats st;
    refactor(mass_free, c_m, c_k, st);
    return st;
  }
  // Forces a refactorisation at the next solve (synchronous: the matrix changed, e.g. the
  // extra stiffness); a pending background refresh is dropped.
  void invalidate();

  const CholmodSolver& factor() const { return *chol_; }
  // The assembly pattern and scatter map (constant while this solver lives; StiffnessFactor).
  const SymmetricAssembler& assembler() const { return assembler_; }
  // Changes whenever the factor in use changes (the compliance cache's column versions).
  long factorVersion() const { return version_; }
  const LinearSolverSettings& settings() const { return settings_; }
  bool refreshPending() const { return pending_ != nullptr; }
  // A background refresh still being computed (a copy of this solver would wait for it).
  bool refreshRunning() const;
  // Background refreshes on or off from now (settings' `async` at construction). Static
  // Newton turns them off: its matrix changes much between iterations (contact sets, load
  // control), and a factor of an older iteration's matrix costs more CG than it saves.
  void setAsync(bool on) {
    if (!on) dropRefresh();
    async_ = on;
  }
  bool async() const { return async_; }
  // While held, a stale factor is not refreshed (CG goes on with it; a solve that cannot
  // converge still refactors): a body about to be replaced by a deferred mesh change leaves
  // the second core to the new body's build.
  void holdRefresh(bool on) { hold_ = on; }
  // Lagged rotations (settings' rotation_drift; TissueBody::freeMotion, doc/method.md "Time
  // integration"): the caller gives the model the factor's rotations before each step, so that
  // the step's matrix is the factor's own. The element rotations the factor in use was made
  // with (empty before the first):
  const std::vector<Mat3>& factorRotations() const { return factor_rot_; }
  // From now on: a refresh captures *current (the rotations of the positions, which the model
  // no longer holds) instead of the model's, and only takeDueRefresh() swaps one in (solve()
  // does not, so that a step's rotations and factor belong together). nullptr: as before.
  void setLaggedRotations(const std::vector<Mat3>* current) {
    capture_ = current;
    swap_in_solve_ = current == nullptr;
  }
  // Swaps in a pending refresh that is due at the next solve() (as that call would), before
  // the step takes the factor's rotations; true if it did (the columns are then to be taken).
  bool takeDueRefresh(LinearSolveStats& st) { return swapDueRefresh(st, 1); }
  // Refresh at the next solve() (unless one is pending): the rotations drifted too far.
  void requestRefresh() {
    if (!pending_) stale_ = true;
  }
  // Tests: every background refresh takes at least this long (a factor that finishes late).
  static void setRefreshDelayForTesting(double ms);

  ~SystemSolver();

 private:
  // A background refresh: the matrix of one call, assembled and factorised off this thread.
  struct Refresh {
    std::unique_ptr<CholmodSolver> factor;  // analysed like chol_, factorised on the thread
    SparseMatrix matrix;                     // the pattern of assembler_, its own values
    std::vector<Mat3> rotations;             // of the requesting call
    VecX mass_free;
    double c_m = 0, c_k = 0;
    ElementBlocks extra;
    long requested_call = 0;
    std::vector<int> column_dofs;            // A^-1 columns asked for, computed after the factor
    Eigen::MatrixXd columns;
    double work_ms = 0;                      // assembly + factorisation (+ columns) on the thread
    std::shared_future<bool> done;           // true: positive definite
  };
  void refactor(const VecX& mass_free, double c_m, double c_k, LinearSolveStats& st);
  void startRefresh(const VecX& mass_free, double c_m, double c_k, LinearSolveStats& st,
                    const std::function<std::vector<int>()>& column_dofs);
  // Waits for the pending refresh and makes it the factor in use (false: it failed, and a
  // synchronous refactorisation is due).
  bool finishRefresh(LinearSolveStats& st);
  // CG iterations on a stale factor before refactorising (synchronous refreshes: those that
  // cost less than a factorisation; asynchronous: max_iterations).
  int staleBudget() const;
  void dropRefresh();
  // Swaps in a pending refresh due at the call `ahead` calls from now (0: this one).
  bool swapDueRefresh(LinearSolveStats& st, long ahead);

  const CorotationalHexModel& model_;
  const DofMap& dofs_;
  LinearSolverSettings settings_;
  SymmetricAssembler assembler_;
  std::unique_ptr<CholmodSolver> chol_;
  long version_ = 0;
  bool stale_ = true;          // refresh the factor (in the background if async)
  int fresh_iterations_ = 0;   // GMRES iterations of the first solve with the factor (nonsymmetric term)
  bool must_refactor_ = false;  // refactorise before this call's solve (the matrix changed)
  bool async_ = true;
  bool hold_ = false;
  long calls_ = 0, calls_since_factor_ = 0;
  std::unique_ptr<Refresh> pending_;
  std::unique_ptr<Refresh> spare_;  // a finished refresh's buffers, reused by the next
  long columns_version_ = -1;       // spare_'s columns belong to this factor version (-1: none to take)
  mutable VecX full_in_, full_out_;
  const ElementBlocks* extra_ = nullptr;
  const OperatorTerm* nonsymmetric_ = nullptr;
  std::vector<Mat3> factor_rot_;                 // the rotations of the factor in use
  bool swap_in_solve_ = true;                    // false with lagged rotations
  const std::vector<Mat3>* capture_ = nullptr;  // lagged rotations: what a refresh captures
};

}  // namespace needle_sim

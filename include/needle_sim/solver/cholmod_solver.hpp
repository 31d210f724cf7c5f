#pragma once
// A thin RAII wrapper over SuiteSparse CHOLMOD for the symmetric positive definite
// systems of each body.
//
// The symbolic analysis (fill-reducing ordering, elimination tree, supernodes) is done
// once per sparsity pattern by analyze(); factorize() only redoes the numeric part, as
// long as the pattern is unchanged. The matrix is passed as the upper triangle of an
// Eigen compressed-column matrix, viewed without copying (stype = 1).
#include <string>

#include <Eigen/Core>

#include "needle_sim/core/types.hpp"

struct cholmod_common_struct;
struct cholmod_factor_struct;
struct cholmod_dense_struct;

namespace needle_sim {

enum class Ordering { Auto, Amd, Metis };

class CholmodSolver {
 public:
  explicit CholmodSolver(Ordering ordering = Ordering::Auto);
  ~CholmodSolver();
  // A copy holds its own copy of the factor (cholmod_copy_factor): solves with it give the
  // same answers as with the original (a simulation copied for a prediction).
  CholmodSolver(const CholmodSolver& other);
  CholmodSolver& operator=(const CholmodSolver&) = delete;

  // Symbolic analysis of the pattern of `upper` (values are ignored).
  void analyze(const SparseMatrix& upper);
  // Numeric factorisation with the pattern analysed last. Returns false if the matrix is
  // not positive definite (the factor is then unusable until the next success).
  bool factorize(const SparseMatrix& upper);
  // x = A^{-1} b with the current factor. Not thread-safe (reuses workspaces).
  void solve(const VecX& b, VecX& x) const;
  // X = A^{-1} B for several right-hand sides at once (one supernodal sweep).
  void solve(const Eigen::MatrixXd& B, Eigen::MatrixXd& X) const;

  bool analyzed() const { return factor_ != nullptr; }
  bool factored() const { return factored_; }
  int size() const { return n_; }
  long analyses() const { return analyses_; }
  long factorizations() const { return factorizations_; }
  // Nonzeros of L and flop count of a factorisation, from the analysis (reports, and the
  // cost of a refactorisation against CG iterations: SystemSolver).
  double factorNonzeros() const;
  double factorFlops() const;
  bool supernodal() const;
  std::string orderingName() const;

 private:
  cholmod_common_struct* common_ = nullptr;
  cholmod_factor_struct* factor_ = nullptr;
  mutable cholmod_dense_struct* x_ = nullptr;  // solve workspaces, reused
  mutable cholmod_dense_struct* y_ = nullptr;
  mutable cholmod_dense_struct* e_ = nullptr;
  Ordering ordering_;
  int n_ = 0;
  double lnz_ = 0, flops_ = 0;
  bool factored_ = false;
  long analyses_ = 0, factorizations_ = 0;
};

}  // namespace needle_sim

#pragma once
// Columns of A^-1 for the constraint solve (doc/method.md, "Constraint solve"): the
// compliance W = H A^-1 H^T needs the columns of the DOFs the constraint rows touch. They
// are cached across steps: a step solves only for DOFs it has not seen before, plus at most
// kRefresh columns computed with an older factorisation (the oldest first), so that a
// refactorisation never costs hundreds of solves in one step (a stale column is the exact
// column of a nearby matrix: it changes the compliance by the factor's drift, which the
// constraint solve tolerates).
#include <unordered_map>
#include <vector>

#include "needle_sim/core/types.hpp"

namespace needle_sim {

class CholmodSolver;

class ComplianceCache {
 public:
  static constexpr int kRefresh = 8;
  // Makes the columns of free_dofs available from `factor` (version: its factorisation count).
  // version: that of the factor (SystemSolver::factorVersion), which columns are tagged with.
  void prepare(const std::vector<int>& free_dofs, const CholmodSolver& factor, long version, int num_free);
  const VecX& column(int free_dof) const { return columns_.at(free_dof).x; }
  bool has(int free_dof) const { return columns_.count(free_dof) > 0; }
  long version(int free_dof) const { return columns_.at(free_dof).version; }
  size_t size() const { return columns_.size(); }
  void clear() { columns_.clear(); }
  // Columns of these DOFs are kept whatever prepare() asks for (wanted soon: the elements ahead
  // of the needles, TissueBody::setElementsAhead); computed only when adopted or prepared.
  void keep(std::vector<int> dofs) { keep_ = std::move(dofs); }
  // Columns prepare() solved for DOFs that had none, so far (not the stale ones it refreshed).
  long solvedNew() const { return solved_new_; }
  // The free DOFs with a column, sorted.
  std::vector<int> dofs() const;
  // Columns computed elsewhere with the factor of `version` (a background refresh's, taken
  // when it is swapped in): they replace the cached ones of those DOFs.
  void adopt(const std::vector<int>& dofs, const Eigen::MatrixXd& X, long version);

 private:
  struct Column {
    VecX x;
    long version;  // factorisation it came from
  };
  std::unordered_map<int, Column> columns_;
  std::vector<int> keep_;
  long solved_new_ = 0;
};

}  // namespace needle_sim

#pragma once
// Map between all nodal DOFs ("full") and the unknowns of the linear systems ("free").
// Prescribed (Dirichlet) DOFs are removed from the systems, which keeps them symmetric
// positive definite for CHOLMOD. Hanging-node elimination (adaptivity) will generalise
// this selection to a weighted prolongation P with A_free = P^T A P.
#include <vector>

#include "needle_sim/core/types.hpp"

namespace needle_sim {

class DofMap {
 public:
  DofMap() = default;
  // prescribed[i] != 0 marks full DOF i as prescribed.
  explicit DofMap(const std::vector<char>& prescribed);

  int numFull() const { return static_cast<int>(free_of_full_.size()); }
  int numFree() const { return static_cast<int>(full_of_free_.size()); }
  int numPrescribed() const { return numFull() - numFree(); }
  // Free index of a full DOF, or -1 if it is prescribed.
  int freeIndex(int full) const { return free_of_full_[full]; }
  bool prescribed(int full) const { return free_of_full_[full] < 0; }
  const std::vector<int>& freeToFull() const { return full_of_free_; }

  void gather(const VecX& full, VecX& free) const;
  // Writes free values into full; prescribed entries are set to zero.
  void scatter(const VecX& free, VecX& full) const;

 private:
  std::vector<int> free_of_full_;
  std::vector<int> full_of_free_;
};

}  // namespace needle_sim

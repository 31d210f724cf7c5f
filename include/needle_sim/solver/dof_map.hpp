#pragma once
// Map between all nodal DOFs ("full") and the unknowns of the linear systems ("free"):
// the prolongation P with x_full = P x_free (+ prescribed values).
//
//  - a free DOF is an unknown: its column of P is a unit vector;
//  - a prescribed (Dirichlet) DOF is not an unknown: its row of P is empty;
//  - a hanging DOF (adaptivity: a node in the middle of a coarser element's edge or face) is
//    a weighted average of master DOFs (edge midpoint 1/2 + 1/2, face centre 1/4 x 4); its
//    row of P holds the masters' weights, expanded recursively down to free DOFs.
// Systems are solved as P^T A P (symmetric positive definite, as CHOLMOD needs); forces and
// lumped masses are gathered with P^T, increments scattered with P.
#include <utility>
#include <vector>

#include "needle_sim/core/types.hpp"

namespace needle_sim {

struct DofWeight {
  int free;
  double weight;
};

class DofMap {
 public:
  DofMap() = default;
  // prescribed[i] != 0 marks full DOF i as prescribed.
  explicit DofMap(const std::vector<char>& prescribed);
  // hanging[i]: masters (full DOF indices, weights) of full DOF i; empty for a DOF that is
  // not hanging. A DOF both prescribed and hanging is prescribed.
  DofMap(const std::vector<char>& prescribed, const std::vector<std::vector<std::pair<int, double>>>& hanging);

  int numFull() const { return static_cast<int>(offset_.size()) - 1; }
  int numFree() const { return static_cast<int>(full_of_free_.size()); }
  // Free index of a full DOF that is itself an unknown, or -1 (prescribed or hanging).
  int freeIndex(int full) const { return free_of_full_[full]; }
  bool prescribed(int full) const { return prescribed_[full] != 0; }
  bool hanging(int full) const { return free_of_full_[full] < 0 && !prescribed_[full]; }
  const std::vector<int>& freeToFull() const { return full_of_free_; }
  // Row `full` of P: the free DOFs and weights it is made of.
  const DofWeight* expansionBegin(int full) const { return entries_.data() + offset_[full]; }
  const DofWeight* expansionEnd(int full) const { return entries_.data() + offset_[full + 1]; }

  // free = P^T full (forces, lumped masses).
  void gather(const VecX& full, VecX& free) const;
  // full = P free (increments); prescribed entries are zero.
  void scatter(const VecX& free, VecX& full) const;
  // Sets every hanging entry of a full vector (positions) to the weighted values of its
  // masters, prescribed masters included.
  void interpolateHanging(VecX& full) const;

 private:
  void build(const std::vector<char>& prescribed, const std::vector<std::vector<std::pair<int, double>>>* hanging);

  std::vector<int> free_of_full_;
  std::vector<int> full_of_free_;
  std::vector<char> prescribed_;
  std::vector<int> offset_;
  std::vector<DofWeight> entries_;
  std::vector<int> hanging_order_;  // hanging DOFs, masters before the DOFs they carry
  std::vector<std::vector<std::pair<int, double>>> hanging_;
};

}  // namespace needle_sim

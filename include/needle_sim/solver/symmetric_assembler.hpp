#pragma once
// Assembly of symmetric element matrices into the upper triangle of a compressed
// column matrix over the free DOFs (the storage CHOLMOD reads with stype = 1).
//
// Elements are given by the free-DOF index of each of their k local DOFs (-1 for a DOF
// that is not an unknown, e.g. prescribed). The sparsity pattern and, for each element,
// the position of each of its k x k entries in the value array are computed once per
// topology; assembling is then a pure scatter-add with no search and no allocation. The
// same class serves the hexahedra (k = 24) and the beam elements (k = 12).
#include <vector>

#include "needle_sim/core/types.hpp"
#include "needle_sim/fem/hex_mesh.hpp"
#include "needle_sim/solver/dof_map.hpp"

namespace needle_sim {

class SymmetricAssembler {
 public:
  // element_dofs holds k entries per element, elements back to back.
  SymmetricAssembler(int num_free, int dofs_per_element, const std::vector<int>& element_dofs);

  const SparseMatrix& matrix() const { return A_; }
  int dofsPerElement() const { return k_; }
  void setZero() { std::fill(A_.valuePtr(), A_.valuePtr() + A_.nonZeros(), 0.0); }
  // A += scale * Ke for element e; Ke is k x k, column-major.
  void addElement(int e, const double* Ke, double scale);
  // A += scale * diag(d) with d over free DOFs.
  void addDiagonal(const VecX& d, double scale);

 private:
  int k_;
  SparseMatrix A_;
  std::vector<int> pos_;   // k*k per element, -1 = skipped
  std::vector<int> diag_;  // value index of each diagonal entry
};

// Free-DOF indices of the 24 DOFs of every hexahedron.
std::vector<int> hexElementDofs(const HexMesh& mesh, const DofMap& dofs);

}  // namespace needle_sim

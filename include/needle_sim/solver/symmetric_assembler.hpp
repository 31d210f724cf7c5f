#pragma once
// Assembly of symmetric element matrices into the upper triangle of a compressed
// column matrix over the free DOFs (the storage CHOLMOD reads with stype = 1).
//
// The sparsity pattern and, for each element, the position of each of its 24x24 entries
// in the value array are computed once per mesh topology; assembling is then a pure
// scatter-add with no search and no allocation.
#include <vector>

#include "needle_sim/core/types.hpp"
#include "needle_sim/fem/hex8.hpp"
#include "needle_sim/fem/hex_mesh.hpp"
#include "needle_sim/solver/dof_map.hpp"

namespace needle_sim {

class SymmetricAssembler {
 public:
  SymmetricAssembler(const HexMesh& mesh, const DofMap& dofs);

  const SparseMatrix& matrix() const { return A_; }
  void setZero() { std::fill(A_.valuePtr(), A_.valuePtr() + A_.nonZeros(), 0.0); }
  // A += scale * Ke for element e (entries touching prescribed DOFs are dropped).
  void addElement(int e, const hex8::Mat24& Ke, double scale);
  // A += scale * diag(d) with d over free DOFs.
  void addDiagonal(const VecX& d, double scale);

 private:
  SparseMatrix A_;
  std::vector<int> pos_;   // 576 per element, -1 = skipped
  std::vector<int> diag_;  // value index of each diagonal entry
};

}  // namespace needle_sim

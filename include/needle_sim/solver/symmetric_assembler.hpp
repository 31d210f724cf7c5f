#pragma once
// Assembly of symmetric element matrices into the upper triangle of a compressed
// column matrix over the free DOFs (the storage CHOLMOD reads with stype = 1), through the
// prolongation P of the DofMap: A_free = P^T A P, element by element.
//
// Each element lists, for each of its k local DOFs, the free DOFs and weights it is made of
// (one entry of weight 1 for an ordinary DOF, none for a prescribed one, several for a
// hanging one). The sparsity pattern and, for each element, the (value position, local
// entry, weight) triplets are computed once per topology; assembling is then a pure
// scatter-add with no search and no allocation. The same class serves the hexahedra
// (k = 24) and the beam elements (k = 12).
#include <vector>

#include "needle_sim/core/types.hpp"
#include "needle_sim/fem/hex_mesh.hpp"
#include "needle_sim/solver/dof_map.hpp"

namespace needle_sim {

// Expanded DOFs of a set of elements with k local DOFs each.
struct ElementDofs {
  int k = 0;
  std::vector<int> offset;           // (elements * k + 1) offsets into entries
  std::vector<DofWeight> entries;
  int numElements() const { return k ? (static_cast<int>(offset.size()) - 1) / k : 0; }
  // Appends one local DOF given by a full DOF of the map.
  void add(const DofMap& dofs, int full) {
    if (offset.empty()) offset.push_back(0);
    for (const DofWeight* e = dofs.expansionBegin(full); e != dofs.expansionEnd(full); ++e) entries.push_back(*e);
    offset.push_back(static_cast<int>(entries.size()));
  }
};

class SymmetricAssembler {
 public:
  SymmetricAssembler(int num_free, const ElementDofs& elements);

  const SparseMatrix& matrix() const { return A_; }
  int dofsPerElement() const { return k_; }
  void setZero() { std::fill(A_.valuePtr(), A_.valuePtr() + A_.nonZeros(), 0.0); }
  // A += scale * P_e^T Ke P_e for element e; Ke is k x k, column-major.
  void addElement(int e, const double* Ke, double scale);
  // A += scale * diag(d) with d over free DOFs.
  void addDiagonal(const VecX& d, double scale);

 private:
  struct Target {
    int pos;   // index into the value array
    int q;     // local entry j * k + i
    double w;  // product of the two DOFs' weights
  };
  int k_;
  SparseMatrix A_;
  std::vector<int> element_offset_;  // into targets_
  std::vector<Target> targets_;
  std::vector<int> diag_;            // value index of each diagonal entry
};

// Expanded DOFs of every hexahedron (k = 24).
ElementDofs hexElementDofs(const HexMesh& mesh, const DofMap& dofs);

}  // namespace needle_sim

#pragma once
// Assembly of symmetric element matrices into the upper triangle of a compressed
// column matrix over the free DOFs (the storage CHOLMOD reads with stype = 1), through the
// prolongation P of the DofMap: A_free = P^T A P, element by element.
//
// Each element lists, for each of its k local DOFs, the free DOFs and weights it is made of
// (one entry of weight 1 for an ordinary DOF, none for a prescribed one, several for a
// hanging one). Per element the m distinct free DOFs it touches, its local-to-free weights,
// and the value positions of its m x m block (upper triangle) are found once per topology, in
// time linear in the pattern (a mark array per column, no search: a mesh change rebuilds
// this). Assembling an element forms P_e^T K_e P_e as a dense m x m block and adds it there:
// no search and no allocation. The same class serves the hexahedra (k = 24) and the beam
// elements (k = 12).
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
  void addElement(int e, const double* Ke, double scale) { addElementTo(A_.valuePtr(), e, Ke, scale); }
  // A += scale * diag(d) with d over free DOFs.
  void addDiagonal(const VecX& d, double scale) { addDiagonalTo(A_.valuePtr(), d, scale); }
  // The same into the values of another matrix with this pattern (a copy of matrix()): the
  // pattern and the scatter map are read only, so another thread may assemble there.
  void addElementTo(double* values, int e, const double* Ke, double scale) const;
  void addDiagonalTo(double* values, const VecX& d, double scale) const;

 private:
  // The block of element e: its m_e distinct free DOFs, from block_offset_[e]; the local DOFs'
  // expansions onto them (local i -> block index, weight), from expand_offset_[e * k]; the
  // value position of each block entry (row index * m_e + column index) whose row <= column,
  // -1 for the others, from pos_offset_[e].
  struct Expansion {
    int j;     // index into the element's block
    double w;  // weight
  };
  int k_;
  SparseMatrix A_;
  std::vector<int> block_offset_, block_dofs_;
  std::vector<int> expand_offset_;
  std::vector<Expansion> expand_;
  std::vector<int> pos_offset_, pos_;
  std::vector<int> diag_;  // value index of each diagonal entry
  int max_block_ = 0;
};

// Expanded DOFs of every hexahedron (k = 24).
ElementDofs hexElementDofs(const HexMesh& mesh, const DofMap& dofs);

}  // namespace needle_sim

#include "needle_sim/solver/symmetric_assembler.hpp"

#include <algorithm>
#include <cassert>

namespace needle_sim {

SymmetricAssembler::SymmetricAssembler(int n, const ElementDofs& el) : k_(el.k) {
  const int k = el.k, ne = el.numElements();
  // 1. Per element its distinct free DOFs (the block), each local DOF's expansion onto the
  //    block, and for each free DOF the elements touching it with its index in their block.
  std::vector<int> mark(n, -1), index(n, -1);
  std::vector<std::vector<std::pair<int, int>>> dof_elements(n);
  block_offset_.assign(ne + 1, 0);
  expand_offset_.assign(static_cast<size_t>(ne) * k + 1, 0);
  for (int e = 0; e < ne; ++e) {
    const int b0 = static_cast<int>(block_dofs_.size());
    for (int i = 0; i < k; ++i) {
      for (int a = el.offset[e * k + i]; a < el.offset[e * k + i + 1]; ++a) {
        const int r = el.entries[a].free;
        if (mark[r] != e) {
          mark[r] = e;
          index[r] = static_cast<int>(block_dofs_.size()) - b0;
          block_dofs_.push_back(r);
          dof_elements[r].emplace_back(e, index[r]);
        }
        expand_.push_back({index[r], el.entries[a].weight});
      }
      expand_offset_[e * k + i + 1] = static_cast<int>(expand_.size());
    }
    block_offset_[e + 1] = static_cast<int>(block_dofs_.size());
    max_block_ = std::max(max_block_, block_offset_[e + 1] - b0);
  }
  // 2. Column c of the upper triangle: the block DOFs r <= c of the elements touching c
  //    (marker: no duplicates), plus the diagonal (always present: the mass).
  std::fill(mark.begin(), mark.end(), -1);
  std::vector<int> outer(n + 1, 0);
  std::vector<int> rows;
  std::vector<std::vector<int>> col_rows(n);
  for (int c = 0; c < n; ++c) {
    rows.clear();
    mark[c] = c;
    rows.push_back(c);
    for (const auto& [e, j] : dof_elements[c])
      for (int t = block_offset_[e]; t < block_offset_[e + 1]; ++t) {
        const int r = block_dofs_[t];
        if (r < c && mark[r] != c) {
          mark[r] = c;
          rows.push_back(r);
        }
      }
    std::sort(rows.begin(), rows.end());
    col_rows[c] = rows;
    outer[c + 1] = outer[c] + static_cast<int>(rows.size());
  }
  A_.resize(n, n);
  A_.resizeNonZeros(outer[n]);
  std::copy(outer.begin(), outer.end(), A_.outerIndexPtr());
  for (int c = 0; c < n; ++c) std::copy(col_rows[c].begin(), col_rows[c].end(), A_.innerIndexPtr() + outer[c]);
  setZero();
  // 3. Value positions of each element's block entries (row <= column), column by column:
  //    the column's row positions in a scatter array, read for each element touching it.
  pos_offset_.assign(ne + 1, 0);
  for (int e = 0; e < ne; ++e) {
    const int m = block_offset_[e + 1] - block_offset_[e];
    pos_offset_[e + 1] = pos_offset_[e] + m * m;
  }
  pos_.assign(pos_offset_[ne], -1);
  std::vector<int> at(n, -1);
  diag_.resize(n);
  for (int c = 0; c < n; ++c) {
    for (int q = outer[c]; q < outer[c + 1]; ++q) at[A_.innerIndexPtr()[q]] = q;
    diag_[c] = at[c];
    for (const auto& [e, jc] : dof_elements[c]) {
      const int b0 = block_offset_[e], m = block_offset_[e + 1] - b0;
      for (int i = 0; i < m; ++i) {
        const int r = block_dofs_[b0 + i];
        if (r <= c) pos_[pos_offset_[e] + i * m + jc] = at[r];
      }
    }
    for (int q = outer[c]; q < outer[c + 1]; ++q) at[A_.innerIndexPtr()[q]] = -1;
  }
}

void SymmetricAssembler::addElementTo(double* v, int e, const double* Ke, double scale) const {
  // The element's block P_e^T K_e P_e (dense, m x m), then its upper triangle into A. A
  // scratch block per thread: the stepping thread and a background refresh may both assemble.
  thread_local std::vector<double> block;
  const int k = k_, b0 = block_offset_[e], m = block_offset_[e + 1] - b0;
  block.assign(static_cast<size_t>(m) * m, 0.0);
  for (int j = 0; j < k; ++j)
    for (int bj = expand_offset_[e * k + j]; bj < expand_offset_[e * k + j + 1]; ++bj) {
      const Expansion& xj = expand_[bj];
      for (int i = 0; i < k; ++i) {
        const double kij = Ke[j * k + i] * xj.w;
        if (kij == 0.0) continue;
        for (int bi = expand_offset_[e * k + i]; bi < expand_offset_[e * k + i + 1]; ++bi)
          block[static_cast<size_t>(expand_[bi].j) * m + xj.j] += expand_[bi].w * kij;
      }
    }
  const int* pos = pos_.data() + pos_offset_[e];
  for (int q = 0; q < m * m; ++q)
    if (pos[q] >= 0) v[pos[q]] += scale * block[q];
}

void SymmetricAssembler::addDiagonalTo(double* v, const VecX& d, double scale) const {
  assert(d.size() == static_cast<int>(diag_.size()));
  for (size_t c = 0; c < diag_.size(); ++c) v[diag_[c]] += scale * d[c];
}

ElementDofs hexElementDofs(const HexMesh& mesh, const DofMap& dofs) {
  ElementDofs out;
  out.k = 24;
  for (int e = 0; e < mesh.numElements(); ++e) {
    const auto& el = mesh.element(e);
    for (int a = 0; a < 8; ++a)
      for (int d = 0; d < 3; ++d) out.add(dofs, 3 * el[a] + d);
  }
  if (out.offset.empty()) out.offset.push_back(0);
  return out;
}

}  // namespace needle_sim

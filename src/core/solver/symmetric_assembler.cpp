#include "needle_sim/solver/symmetric_assembler.hpp"

#include <algorithm>
#include <cassert>

namespace needle_sim {

SymmetricAssembler::SymmetricAssembler(int n, const ElementDofs& el) : k_(el.k) {
  const int k = el.k, ne = el.numElements();
  // Free DOFs each element touches (its local DOFs' expansions, duplicates removed), and
  // the elements touching each free DOF.
  std::vector<int> mark(n, -1);
  std::vector<int> el_off(ne + 1, 0), el_dofs;
  std::vector<std::vector<int>> dof_elements(n);
  for (int e = 0; e < ne; ++e) {
    for (int a = el.offset[e * k]; a < el.offset[(e + 1) * k]; ++a) {
      const int r = el.entries[a].free;
      if (mark[r] == e) continue;
      mark[r] = e;
      el_dofs.push_back(r);
      dof_elements[r].push_back(e);
    }
    el_off[e + 1] = static_cast<int>(el_dofs.size());
  }
  // Column c of the upper triangle: the DOFs r <= c of the elements touching c, found with a
  // marker (no duplicates to sort away), plus the diagonal (always present: the mass).
  std::fill(mark.begin(), mark.end(), -1);
  std::vector<std::vector<int>> rows(n);
  for (int c = 0; c < n; ++c) {
    auto& v = rows[c];
    mark[c] = c;
    v.push_back(c);
    for (int e : dof_elements[c])
      for (int t = el_off[e]; t < el_off[e + 1]; ++t) {
        const int r = el_dofs[t];
        if (r < c && mark[r] != c) {
          mark[r] = c;
          v.push_back(r);
        }
      }
  }
  auto forPairs = [&](int e, auto&& fn) {
    for (int j = 0; j < k; ++j)
      for (int i = 0; i < k; ++i)
        for (int a = el.offset[e * k + i]; a < el.offset[e * k + i + 1]; ++a)
          for (int b = el.offset[e * k + j]; b < el.offset[e * k + j + 1]; ++b) {
            const DofWeight &ri = el.entries[a], &rj = el.entries[b];
            if (ri.free <= rj.free) fn(ri.free, rj.free, j * k + i, ri.weight * rj.weight);
          }
  };
  std::vector<int> outer(n + 1, 0);
  for (int c = 0; c < n; ++c) {
    auto& v = rows[c];
    std::sort(v.begin(), v.end());
    outer[c + 1] = outer[c] + static_cast<int>(v.size());
  }
  A_.resize(n, n);
  A_.resizeNonZeros(outer[n]);
  std::copy(outer.begin(), outer.end(), A_.outerIndexPtr());
  for (int c = 0; c < n; ++c) std::copy(rows[c].begin(), rows[c].end(), A_.innerIndexPtr() + outer[c]);
  setZero();

  auto find = [&](int row, int col) {
    const int* b = A_.innerIndexPtr() + outer[col];
    const int* e = A_.innerIndexPtr() + outer[col + 1];
    const int* it = std::lower_bound(b, e, row);
    assert(it != e && *it == row);
    return static_cast<int>(it - A_.innerIndexPtr());
  };
  element_offset_.assign(ne + 1, 0);
  for (int e = 0; e < ne; ++e) {
    forPairs(e, [&](int r, int c, int q, double w) { targets_.push_back({find(r, c), q, w}); });
    element_offset_[e + 1] = static_cast<int>(targets_.size());
  }
  diag_.resize(n);
  for (int c = 0; c < n; ++c) diag_[c] = find(c, c);
}

void SymmetricAssembler::addElement(int e, const double* Ke, double scale) {
  double* v = A_.valuePtr();
  for (int t = element_offset_[e]; t < element_offset_[e + 1]; ++t) {
    const Target& tg = targets_[t];
    v[tg.pos] += scale * tg.w * Ke[tg.q];
  }
}

void SymmetricAssembler::addDiagonal(const VecX& d, double scale) {
  assert(d.size() == static_cast<int>(diag_.size()));
  double* v = A_.valuePtr();
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

#include "needle_sim/solver/symmetric_assembler.hpp"

#include <algorithm>
#include <cassert>

namespace needle_sim {

SymmetricAssembler::SymmetricAssembler(int n, int k, const std::vector<int>& element_dofs) : k_(k) {
  assert(k > 0 && element_dofs.size() % k == 0);
  const size_t ne = element_dofs.size() / k;
  // Column-wise row lists of the upper triangle.
  std::vector<std::vector<int>> rows(n);
  for (size_t e = 0; e < ne; ++e) {
    const int* r = element_dofs.data() + e * k;
    for (int i = 0; i < k; ++i)
      for (int j = 0; j < k; ++j)
        if (r[i] >= 0 && r[j] >= 0 && r[i] <= r[j]) rows[r[j]].push_back(r[i]);
  }
  for (int c = 0; c < n; ++c) rows[c].push_back(c);  // diagonal always present (mass)
  std::vector<int> outer(n + 1, 0);
  for (int c = 0; c < n; ++c) {
    auto& v = rows[c];
    std::sort(v.begin(), v.end());
    v.erase(std::unique(v.begin(), v.end()), v.end());
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
  pos_.assign(ne * k * k, -1);
  for (size_t e = 0; e < ne; ++e) {
    const int* r = element_dofs.data() + e * k;
    int* p = pos_.data() + e * k * k;
    for (int j = 0; j < k; ++j)
      for (int i = 0; i < k; ++i)
        if (r[i] >= 0 && r[j] >= 0 && r[i] <= r[j]) p[j * k + i] = find(r[i], r[j]);
  }
  diag_.resize(n);
  for (int c = 0; c < n; ++c) diag_[c] = find(c, c);
}

void SymmetricAssembler::addElement(int e, const double* Ke, double scale) {
  const int kk = k_ * k_;
  const int* p = pos_.data() + static_cast<size_t>(e) * kk;
  double* v = A_.valuePtr();
  for (int q = 0; q < kk; ++q)
    if (p[q] >= 0) v[p[q]] += scale * Ke[q];
}

void SymmetricAssembler::addDiagonal(const VecX& d, double scale) {
  assert(d.size() == static_cast<int>(diag_.size()));
  double* v = A_.valuePtr();
  for (size_t c = 0; c < diag_.size(); ++c) v[diag_[c]] += scale * d[c];
}

std::vector<int> hexElementDofs(const HexMesh& mesh, const DofMap& dofs) {
  std::vector<int> out(static_cast<size_t>(mesh.numElements()) * 24);
  for (int e = 0; e < mesh.numElements(); ++e) {
    const auto& el = mesh.element(e);
    for (int a = 0; a < 8; ++a)
      for (int d = 0; d < 3; ++d) out[24 * e + 3 * a + d] = dofs.freeIndex(3 * el[a] + d);
  }
  return out;
}

}  // namespace needle_sim

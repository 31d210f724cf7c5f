#include "needle_sim/solver/symmetric_assembler.hpp"

#include <algorithm>
#include <cassert>

namespace needle_sim {

SymmetricAssembler::SymmetricAssembler(const HexMesh& mesh, const DofMap& dofs) {
  const int n = dofs.numFree();
  const int ne = mesh.numElements();
  auto freeDofs = [&](int e, std::array<int, 24>& r) {
    const auto& el = mesh.element(e);
    for (int a = 0; a < 8; ++a)
      for (int d = 0; d < 3; ++d) r[3 * a + d] = dofs.freeIndex(3 * el[a] + d);
  };
  // Column-wise row lists of the upper triangle.
  std::vector<std::vector<int>> rows(n);
  std::array<int, 24> r;
  for (int e = 0; e < ne; ++e) {
    freeDofs(e, r);
    for (int i = 0; i < 24; ++i)
      for (int j = 0; j < 24; ++j)
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
  A_.makeCompressed();
  setZero();

  auto find = [&](int row, int col) {
    const int* b = A_.innerIndexPtr() + outer[col];
    const int* e = A_.innerIndexPtr() + outer[col + 1];
    const int* it = std::lower_bound(b, e, row);
    assert(it != e && *it == row);
    return static_cast<int>(it - A_.innerIndexPtr());
  };
  pos_.assign(static_cast<size_t>(ne) * 576, -1);
  for (int e = 0; e < ne; ++e) {
    freeDofs(e, r);
    int* p = pos_.data() + static_cast<size_t>(e) * 576;
    for (int j = 0; j < 24; ++j)
      for (int i = 0; i < 24; ++i)
        if (r[i] >= 0 && r[j] >= 0 && r[i] <= r[j]) p[j * 24 + i] = find(r[i], r[j]);
  }
  diag_.resize(n);
  for (int c = 0; c < n; ++c) diag_[c] = find(c, c);
}

void SymmetricAssembler::addElement(int e, const hex8::Mat24& Ke, double scale) {
  const int* p = pos_.data() + static_cast<size_t>(e) * 576;
  double* v = A_.valuePtr();
  const double* k = Ke.data();  // column-major, same order as p
  for (int q = 0; q < 576; ++q)
    if (p[q] >= 0) v[p[q]] += scale * k[q];
}

void SymmetricAssembler::addDiagonal(const VecX& d, double scale) {
  assert(d.size() == static_cast<int>(diag_.size()));
  double* v = A_.valuePtr();
  for (size_t c = 0; c < diag_.size(); ++c) v[diag_[c]] += scale * d[c];
}

}  // namespace needle_sim

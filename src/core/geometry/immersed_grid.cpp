#include "needle_sim/geometry/immersed_grid.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <unordered_map>

namespace needle_sim {

void ImmersedGrid::layout(const Vec3& lo, const Vec3& hi, const ImmersedGridSettings& s, Vec3i& dims, Vec3& origin,
                          Vec3& h) {
  const Vec3 ext = hi - lo;
  if (s.cells) {
    dims = *s.cells;
    h = ext.cwiseQuotient(dims.cast<double>());
    origin = lo;
  } else {
    const double c = s.cell_size.value_or(ext.maxCoeff() / 8);
    for (int d = 0; d < 3; ++d) dims[d] = std::max(1, static_cast<int>(std::ceil(ext[d] / c - 1e-9)));
    h = Vec3::Constant(c);
    origin = 0.5 * (lo + hi) - 0.5 * dims.cast<double>().cwiseProduct(h);
  }
  for (int r = 0; r < s.refine; ++r) {
    dims *= 2;
    h /= 2;
  }
}

ImmersedGrid::ImmersedGrid(std::shared_ptr<const TriangleMesh> surface, const ImmersedGridSettings& s)
    : settings_(s), inside_(surface) {
  const TriangleMesh& m = *surface;
  layout(m.boundsMin(), m.boundsMax(), s, dims_, lo_, h_);
  if (!(h_.minCoeff() > 0)) throw std::invalid_argument("the surface is flat: its bounding box has no volume");

  auto cellIndex = [&](int i, int j, int k) { return i + dims_[0] * (j + static_cast<long>(dims_[1]) * k); };
  // Cells holding a surface vertex are kept even when sampling misses their sliver, so that
  // every surface vertex can be embedded.
  std::vector<char> has_vertex(static_cast<size_t>(dims_.cast<long>().prod()), 0);
  for (const auto& v : m.vertices()) {
    Vec3i c;
    for (int d = 0; d < 3; ++d) c[d] = std::clamp(static_cast<int>(std::floor((v[d] - lo_[d]) / h_[d])), 0, dims_[d] - 1);
    has_vertex[cellIndex(c[0], c[1], c[2])] = 1;
  }
  std::unordered_map<long, int> node_id;
  std::vector<Vec3> nodes;
  std::vector<HexElement> elements;
  auto node = [&](int i, int j, int k) {
    const long key = i + (dims_[0] + 1L) * (j + (dims_[1] + 1L) * k);
    auto it = node_id.find(key);
    if (it != node_id.end()) return it->second;
    const int id = static_cast<int>(nodes.size());
    nodes.push_back(lo_ + Vec3(i, j, k).cwiseProduct(h_));
    node_id.emplace(key, id);
    return id;
  };
  std::vector<double> floored;
  for (int k = 0; k < dims_[2]; ++k)
    for (int j = 0; j < dims_[1]; ++j)
      for (int i = 0; i < dims_[0]; ++i) {
        const Vec3 a = lo_ + Vec3(i, j, k).cwiseProduct(h_);
        const double f = inside_.boxFraction(a, a + h_, s.samples);
        if (f <= 0 && !has_vertex[cellIndex(i, j, k)]) continue;
        elements.push_back({node(i, j, k), node(i + 1, j, k), node(i + 1, j + 1, k), node(i, j + 1, k),
                            node(i, j, k + 1), node(i + 1, j, k + 1), node(i + 1, j + 1, k + 1), node(i, j + 1, k + 1)});
        fraction_.push_back(f);
        floored.push_back(std::max(f, s.min_fraction));
      }
  if (elements.empty()) throw std::invalid_argument("no grid cell lies inside the surface");
  mesh_ = HexMesh(std::move(nodes), std::move(elements));
  mesh_.setFractions(std::move(floored));
}

double ImmersedGrid::volume() const {
  double v = 0;
  for (double f : fraction_) v += f;
  return v * h_.prod();
}

}  // namespace needle_sim

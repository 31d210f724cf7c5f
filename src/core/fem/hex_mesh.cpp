#include "needle_sim/fem/hex_mesh.hpp"

#include <algorithm>
#include <map>
#include <stdexcept>

#include "needle_sim/fem/hex8.hpp"

namespace needle_sim {

HexMesh::HexMesh(std::vector<Vec3> nodes, std::vector<HexElement> elements)
    : nodes_(std::move(nodes)), elements_(std::move(elements)) {
  for (const auto& el : elements_)
    for (int n : el)
      if (n < 0 || n >= numNodes()) throw std::invalid_argument("HexMesh: element node out of range");
}

HexMesh HexMesh::mappedBlock(const std::array<Vec3, 8>& corners, const Vec3i& cells) {
  if ((cells.array() < 1).any()) throw std::invalid_argument("HexMesh: cells must be >= 1");
  const int nx = cells[0], ny = cells[1], nz = cells[2];
  std::vector<Vec3> nodes;
  nodes.reserve(static_cast<size_t>(nx + 1) * (ny + 1) * (nz + 1));
  for (int k = 0; k <= nz; ++k)
    for (int j = 0; j <= ny; ++j)
      for (int i = 0; i <= nx; ++i) {
        const Eigen::Vector3d xi(-1.0 + 2.0 * i / nx, -1.0 + 2.0 * j / ny, -1.0 + 2.0 * k / nz);
        const auto N = hex8::shape(xi);
        Vec3 p = Vec3::Zero();
        for (int a = 0; a < 8; ++a) p += N[a] * corners[a];
        nodes.push_back(p);
      }
  auto id = [&](int i, int j, int k) { return i + (nx + 1) * (j + (ny + 1) * k); };
  std::vector<HexElement> elements;
  elements.reserve(static_cast<size_t>(nx) * ny * nz);
  for (int k = 0; k < nz; ++k)
    for (int j = 0; j < ny; ++j)
      for (int i = 0; i < nx; ++i)
        elements.push_back({id(i, j, k), id(i + 1, j, k), id(i + 1, j + 1, k), id(i, j + 1, k),
                            id(i, j, k + 1), id(i + 1, j, k + 1), id(i + 1, j + 1, k + 1),
                            id(i, j + 1, k + 1)});
  return HexMesh(std::move(nodes), std::move(elements));
}

HexMesh HexMesh::box(const Vec3& lo, const Vec3& hi, const Vec3i& cells) {
  std::array<Vec3, 8> c;
  for (int a = 0; a < 8; ++a)
    for (int d = 0; d < 3; ++d) c[a][d] = hex8::kCornerSigns[a][d] < 0 ? lo[d] : hi[d];
  HexMesh m = mappedBlock(c, cells);
  // Snap grid coordinates exactly (the trilinear map is exact, this only removes round-off).
  const int nx = cells[0], ny = cells[1];
  for (int n = 0; n < m.numNodes(); ++n) {
    const int i = n % (nx + 1), j = (n / (nx + 1)) % (ny + 1), k = n / ((nx + 1) * (ny + 1));
    const Vec3 t(double(i) / cells[0], double(j) / cells[1], double(k) / cells[2]);
    m.nodes_[n] = lo.array() + t.array() * (hi - lo).array();
  }
  return m;
}

VecX HexMesh::restPositions() const {
  VecX x(numDofs());
  for (int i = 0; i < numNodes(); ++i) x.segment<3>(3 * i) = nodes_[i];
  return x;
}

Eigen::Matrix<double, 8, 3> HexMesh::elementCorners(int e) const {
  Eigen::Matrix<double, 8, 3> X;
  for (int a = 0; a < 8; ++a) X.row(a) = nodes_[elements_[e][a]].transpose();
  return X;
}

std::vector<BoundaryFace> HexMesh::boundaryFaces() const {
  // A face is on the boundary when its sorted node set occurs once.
  std::map<std::array<int, 4>, std::pair<int, int>> seen;  // key -> (count, first index)
  std::vector<BoundaryFace> faces;
  for (int e = 0; e < numElements(); ++e)
    for (int f = 0; f < 6; ++f) {
      BoundaryFace bf{e, f, {}};
      for (int q = 0; q < 4; ++q) bf.nodes[q] = elements_[e][hex8::kFaces[f][q]];
      auto key = bf.nodes;
      std::sort(key.begin(), key.end());
      auto it = seen.find(key);
      if (it == seen.end()) {
        seen.emplace(key, std::make_pair(1, static_cast<int>(faces.size())));
        faces.push_back(bf);
      } else {
        it->second.first++;
      }
    }
  std::vector<BoundaryFace> out;
  for (const auto& kv : seen)
    if (kv.second.first == 1 && !interface_faces_.count(kv.first)) out.push_back(faces[kv.second.second]);
  std::sort(out.begin(), out.end(), [](const BoundaryFace& a, const BoundaryFace& b) {
    return a.element != b.element ? a.element < b.element : a.face < b.face;
  });
  return out;
}

Vec3 HexMesh::boundsMin() const {
  Vec3 m = Vec3::Constant(std::numeric_limits<double>::infinity());
  for (const auto& p : nodes_) m = m.cwiseMin(p);
  return m;
}
Vec3 HexMesh::boundsMax() const {
  Vec3 m = Vec3::Constant(-std::numeric_limits<double>::infinity());
  for (const auto& p : nodes_) m = m.cwiseMax(p);
  return m;
}

}  // namespace needle_sim

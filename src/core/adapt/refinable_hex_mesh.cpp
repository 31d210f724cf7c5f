#include "needle_sim/adapt/refinable_hex_mesh.hpp"

#include <algorithm>
#include <set>
#include <stdexcept>

#include "needle_sim/fem/hex8.hpp"

namespace needle_sim {

namespace {
// The 12 edges of a hexahedron (VTK corner order).
const int kEdges[12][2] = {{0, 1}, {1, 2}, {2, 3}, {3, 0}, {4, 5}, {5, 6},
                           {6, 7}, {7, 4}, {0, 4}, {1, 5}, {2, 6}, {3, 7}};
// Grid index (0..2 per axis) of each VTK corner.
int cornerIndex(int a, int axis) { return hex8::kCornerSigns[a][axis] < 0 ? 0 : 2; }
}  // namespace

RefinableHexMesh::RefinableHexMesh(const HexMesh& coarse)
    : nodes_(coarse.nodes()), use_(coarse.numNodes(), 0), sources_(coarse.numNodes()) {
  for (const auto& el : coarse.elements()) {
    Cell c;
    c.nodes = el;
    cells_.push_back(c);
    for (int a : el) ++use_[a];
  }
}

int RefinableHexMesh::numLeaves() const {
  int n = 0;
  for (int c = 0; c < numCells(); ++c) n += isActive(c);
  return n;
}

int RefinableHexMesh::numActiveNodes() const {
  int n = 0;
  for (int u : use_) n += u > 0;
  return n;
}

int RefinableHexMesh::findEdgeMid(int a, int b) const {
  auto it = edge_mid_.find({std::min(a, b), std::max(a, b)});
  return it == edge_mid_.end() ? -1 : it->second;
}

int RefinableHexMesh::findFaceMid(std::array<int, 4> f) const {
  std::sort(f.begin(), f.end());
  auto it = face_mid_.find(f);
  return it == face_mid_.end() ? -1 : it->second;
}

int RefinableHexMesh::edgeMid(int a, int b, bool create) {
  const int m = findEdgeMid(a, b);
  if (m >= 0 || !create) return m;
  nodes_.push_back(0.5 * (nodes_[a] + nodes_[b]));
  use_.push_back(0);
  sources_.push_back({a, b});
  const int id = static_cast<int>(nodes_.size()) - 1;
  edge_mid_[{std::min(a, b), std::max(a, b)}] = id;
  return id;
}

int RefinableHexMesh::faceMid(const std::array<int, 4>& f, bool create) {
  const int m = findFaceMid(f);
  if (m >= 0 || !create) return m;
  nodes_.push_back(0.25 * (nodes_[f[0]] + nodes_[f[1]] + nodes_[f[2]] + nodes_[f[3]]));
  use_.push_back(0);
  sources_.push_back({f[0], f[1], f[2], f[3]});
  const int id = static_cast<int>(nodes_.size()) - 1;
  auto key = f;
  std::sort(key.begin(), key.end());
  face_mid_[key] = id;
  return id;
}

void RefinableHexMesh::split(int ci) {
  if (cells_[ci].former >= 0) {  // children merged back earlier: the same cells again
    const int first = cells_[ci].former;
    for (int k = 0; k < 8; ++k)
      for (int a : cells_[first + k].nodes) ++use_[a];
    for (int a : cells_[ci].nodes) --use_[a];
    cells_[ci].child = first;
    cells_[ci].former = -1;
    return;
  }
  // The 27 nodes of the 3x3x3 template, by grid index (i, j, k).
  int grid[3][3][3];
  const std::array<int, 8> cn = cells_[ci].nodes;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      for (int k = 0; k < 3; ++k) grid[i][j][k] = -1;
  for (int a = 0; a < 8; ++a) grid[cornerIndex(a, 0)][cornerIndex(a, 1)][cornerIndex(a, 2)] = cn[a];
  for (const auto& e : kEdges) {
    const int a = e[0], b = e[1];
    const int id = edgeMid(cn[a], cn[b], true);
    grid[(cornerIndex(a, 0) + cornerIndex(b, 0)) / 2][(cornerIndex(a, 1) + cornerIndex(b, 1)) / 2]
        [(cornerIndex(a, 2) + cornerIndex(b, 2)) / 2] = id;
  }
  for (const auto& f : hex8::kFaces) {
    const std::array<int, 4> fn = {cn[f[0]], cn[f[1]], cn[f[2]], cn[f[3]]};
    int gi = 0, gj = 0, gk = 0;
    for (int q = 0; q < 4; ++q) {
      gi += cornerIndex(f[q], 0);
      gj += cornerIndex(f[q], 1);
      gk += cornerIndex(f[q], 2);
    }
    grid[gi / 4][gj / 4][gk / 4] = faceMid(fn, true);
  }
  if (cells_[ci].centre < 0) {
    // Body centre: the trilinear map at xi = 0.
    Vec3 p = Vec3::Zero();
    for (int a = 0; a < 8; ++a) p += 0.125 * nodes_[cn[a]];
    nodes_.push_back(p);
    use_.push_back(0);
    sources_.push_back(std::vector<int>(cn.begin(), cn.end()));
    cells_[ci].centre = static_cast<int>(nodes_.size()) - 1;
  }
  grid[1][1][1] = cells_[ci].centre;
  // Eight children in lexicographic order of their lower corner.
  const int first = static_cast<int>(cells_.size());
  for (int k = 0; k < 2; ++k)
    for (int j = 0; j < 2; ++j)
      for (int i = 0; i < 2; ++i) {
        Cell child;
        for (int a = 0; a < 8; ++a)
          child.nodes[a] = grid[i + cornerIndex(a, 0) / 2][j + cornerIndex(a, 1) / 2][k + cornerIndex(a, 2) / 2];
        child.level = cells_[ci].level + 1;
        child.parent = ci;
        cells_.push_back(child);
        for (int a : child.nodes) ++use_[a];
      }
  for (int a : cells_[ci].nodes) --use_[a];
  cells_[ci].child = first;
}

// A leaf violates the 2:1 balance when a leaf two levels finer touches one of its edges or
// faces: an active node at a quarter of one of its edges, or at the centre of a quarter of
// one of its faces.
bool RefinableHexMesh::violatesBalance(int ci) const {
  const Cell& c = cells_[ci];
  for (const auto& e : kEdges) {
    const int a = c.nodes[e[0]], b = c.nodes[e[1]];
    const int m = findEdgeMid(a, b);
    if (m < 0) continue;
    if (activeNode(findEdgeMid(a, m)) || activeNode(findEdgeMid(m, b))) return true;
  }
  for (const auto& f : hex8::kFaces) {
    const std::array<int, 4> fn = {c.nodes[f[0]], c.nodes[f[1]], c.nodes[f[2]], c.nodes[f[3]]};
    const int centre = findFaceMid(fn);
    if (centre < 0) continue;
    int m[4];
    for (int q = 0; q < 4; ++q) m[q] = findEdgeMid(fn[q], fn[(q + 1) % 4]);
    for (int q = 0; q < 4; ++q) {
      if (m[q] < 0 || m[(q + 3) % 4] < 0) continue;
      if (activeNode(findEdgeMid(m[q], centre))) return true;
      if (activeNode(findFaceMid({fn[q], m[q], centre, m[(q + 3) % 4]}))) return true;
    }
  }
  return false;
}

int RefinableHexMesh::refine(const std::vector<int>& cells) {
  int count = 0;
  for (int c : cells)
    if (c >= 0 && c < numCells() && isActive(c)) {
      split(c);
      ++count;
    }
  // Restore the 2:1 balance: refine offending leaves until none is left.
  for (bool changed = count > 0; changed;) {
    changed = false;
    const int n = numCells();
    for (int c = 0; c < n; ++c)
      if (isActive(c) && violatesBalance(c)) {
        split(c);
        ++count;
        changed = true;
      }
  }
  return count;
}

int RefinableHexMesh::coarsen(const std::vector<int>& parents) {
  int count = 0;
  for (int p : parents) {
    if (p < 0 || p >= numCells() || isLeaf(p)) continue;
    const int first = cells_[p].child;
    bool leaves = true;
    for (int k = 0; k < 8; ++k) leaves = leaves && isActive(first + k);
    if (!leaves) continue;
    // Tentatively merge, undo if a neighbour would then be two levels finer.
    for (int k = 0; k < 8; ++k)
      for (int a : cells_[first + k].nodes) --use_[a];
    for (int a : cells_[p].nodes) ++use_[a];
    cells_[p].child = -1;
    if (violatesBalance(p)) {
      cells_[p].child = first;
      for (int a : cells_[p].nodes) --use_[a];
      for (int k = 0; k < 8; ++k)
        for (int a : cells_[first + k].nodes) ++use_[a];
      continue;
    }
    // The children stay in the forest, inactive, so that indices remain stable and
    // refining again brings the same cells back.
    cells_[p].former = first;
    ++count;
  }
  return count;
}

int RefinableHexMesh::Active::numHanging() const {
  int n = 0;
  for (const auto& h : hanging) n += !h.empty();
  return n;
}

RefinableHexMesh::Active RefinableHexMesh::active() const {
  Active out;
  std::vector<int> index(nodes_.size(), -1);
  std::vector<Vec3> pts;
  std::vector<HexElement> els;
  for (int c = 0; c < numCells(); ++c) {
    if (!isActive(c)) continue;
    HexElement el;
    for (int a = 0; a < 8; ++a) {
      const int id = cells_[c].nodes[a];
      if (index[id] < 0) {
        index[id] = static_cast<int>(pts.size());
        pts.push_back(nodes_[id]);
        out.node_id.push_back(id);
      }
      el[a] = index[id];
    }
    els.push_back(el);
    out.level.push_back(cells_[c].level);
    out.cell.push_back(c);
  }
  out.hanging.assign(pts.size(), {});
  std::set<std::array<int, 4>> interface;
  // Hanging nodes: active nodes in the middle of an active leaf's edge or face.
  for (size_t e = 0; e < els.size(); ++e) {
    const Cell& c = cells_[out.cell[e]];
    for (const auto& ed : kEdges) {
      const int m = findEdgeMid(c.nodes[ed[0]], c.nodes[ed[1]]);
      if (m < 0 || index[m] < 0) continue;
      out.hanging[index[m]] = {{index[c.nodes[ed[0]]], 0.5}, {index[c.nodes[ed[1]]], 0.5}};
    }
    for (const auto& f : hex8::kFaces) {
      const int m = findFaceMid({c.nodes[f[0]], c.nodes[f[1]], c.nodes[f[2]], c.nodes[f[3]]});
      if (m < 0 || index[m] < 0) continue;
      // A coarse face with finer neighbours: it and its four quarters are interior.
      std::array<int, 4> key = {index[c.nodes[f[0]]], index[c.nodes[f[1]]], index[c.nodes[f[2]]], index[c.nodes[f[3]]]};
      std::sort(key.begin(), key.end());
      interface.insert(key);
      for (int q = 0; q < 4; ++q) {
        const int a = c.nodes[f[q]];
        const int e1 = findEdgeMid(a, c.nodes[f[(q + 1) % 4]]), e0 = findEdgeMid(a, c.nodes[f[(q + 3) % 4]]);
        if (e1 < 0 || e0 < 0 || index[e1] < 0 || index[e0] < 0) continue;
        std::array<int, 4> quarter = {index[a], index[e1], index[m], index[e0]};
        std::sort(quarter.begin(), quarter.end());
        interface.insert(quarter);
      }
      out.hanging[index[m]] = {{index[c.nodes[f[0]]], 0.25},
                               {index[c.nodes[f[1]]], 0.25},
                               {index[c.nodes[f[2]]], 0.25},
                               {index[c.nodes[f[3]]], 0.25}};
    }
  }
  out.mesh = HexMesh(std::move(pts), std::move(els));
  out.mesh.setInterfaceFaces(std::move(interface));
  return out;
}

}  // namespace needle_sim

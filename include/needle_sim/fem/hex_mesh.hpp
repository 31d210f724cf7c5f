#pragma once
// A hexahedral mesh: rest node positions and 8-node elements (VTK order).
//
// Meshes are built as structured grids, either over an axis-aligned box or over a
// "mapped block" (any convex hexahedron given by 8 corners, mapped trilinearly; this
// covers Cook's membrane). Adaptivity will later add refined elements and hanging nodes
// on top of this representation, so nothing here assumes a grid after construction.
#include <array>
#include <set>
#include <vector>

#include "needle_sim/core/types.hpp"

namespace needle_sim {

using HexElement = std::array<int, 8>;

struct BoundaryFace {
  int element;
  int face;                 // index into hex8::kFaces
  std::array<int, 4> nodes;  // global node ids
};

class HexMesh {
 public:
  HexMesh() = default;
  HexMesh(std::vector<Vec3> nodes, std::vector<HexElement> elements);

  // Structured nx x ny x nz grid over the trilinear block with the given 8 corners
  // (VTK order). Node (i,j,k) has index i + (nx+1)*(j + (ny+1)*k).
  static HexMesh mappedBlock(const std::array<Vec3, 8>& corners, const Vec3i& cells);
  static HexMesh box(const Vec3& min, const Vec3& max, const Vec3i& cells);

  int numNodes() const { return static_cast<int>(nodes_.size()); }
  int numElements() const { return static_cast<int>(elements_.size()); }
  int numDofs() const { return 3 * numNodes(); }
  const std::vector<Vec3>& nodes() const { return nodes_; }
  const std::vector<HexElement>& elements() const { return elements_; }
  const Vec3& node(int i) const { return nodes_[i]; }
  const HexElement& element(int e) const { return elements_[e]; }

  // Rest positions as one flat vector (3n).
  VecX restPositions() const;
  // Rest corner coordinates of element e as an 8x3 matrix.
  Eigen::Matrix<double, 8, 3> elementCorners(int e) const;
  // Element faces not shared with another element and not on a non-conforming interface.
  std::vector<BoundaryFace> boundaryFaces() const;
  // Faces (node sets) of a refined mesh that are interior although no other element has the
  // same four nodes: a coarse face next to four finer ones, and those four (hanging nodes).
  void setInterfaceFaces(std::set<std::array<int, 4>> sorted_keys) { interface_faces_ = std::move(sorted_keys); }
  Vec3 boundsMin() const;
  Vec3 boundsMax() const;

  // Volume fraction of each element that is material (immersed geometry); 1 when unset.
  // Stiffness and mass of element e are weighted by it.
  double fraction(int e) const { return fractions_.empty() ? 1.0 : fractions_[e]; }
  bool hasFractions() const { return !fractions_.empty(); }
  void setFractions(std::vector<double> f) { fractions_ = std::move(f); }

  // Lets tests perturb interior nodes (distorted-mesh patch tests).
  void setNode(int i, const Vec3& p) { nodes_[i] = p; }

 private:
  std::vector<Vec3> nodes_;
  std::vector<HexElement> elements_;
  std::set<std::array<int, 4>> interface_faces_;
  std::vector<double> fractions_;
};

}  // namespace needle_sim

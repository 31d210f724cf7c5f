#pragma once
// Material points embedded in the hexahedral mesh (probes now; constraint points,
// targets and surface vertices later): an element and trilinear weights, so the point
// moves with the finite-element field. Re-embedding after a mesh change uses the rest
// position, which is why it is kept.
#include <vector>

#include "needle_sim/core/types.hpp"
#include "needle_sim/fem/hex8.hpp"
#include "needle_sim/fem/hex_mesh.hpp"

namespace needle_sim {

struct EmbeddedPoint {
  Vec3 rest = Vec3::Zero();  // rest position (material coordinates)
  int element = -1;
  Vec3 xi = Vec3::Zero();    // natural coordinates in the element
  hex8::Vec8 weights = hex8::Vec8::Zero();

  // Interpolated position (or displacement, velocity) from a flat nodal vector.
  Vec3 interpolate(const HexMesh& mesh, const VecX& nodal) const {
    Vec3 p = Vec3::Zero();
    for (int a = 0; a < 8; ++a) p += weights[a] * node3(nodal, mesh.element(element)[a]);
    return p;
  }
};

// Finds the element containing a rest-space point with a uniform bin grid over element
// bounding boxes (constant-time lookups for the thousands of surface vertices to come).
class PointLocator {
 public:
  explicit PointLocator(const HexMesh& mesh);
  // False when the point lies outside every element (with a 1e-9 tolerance in xi).
  bool locate(const Vec3& p, EmbeddedPoint& out) const;
  // The material point of the nearest element (natural coordinates clamped to the element)
  // among those binned around p: for points a rounding error outside the mesh. False only
  // when no element is near.
  bool locateNearest(const Vec3& p, EmbeddedPoint& out) const;

 private:
  const HexMesh& mesh_;
  Vec3 lo_, hi_, cell_;
  Vec3i dims_;
  std::vector<std::vector<int>> bins_;
  // Each element's bounding box, widened by a little more than locate's tolerance: a point
  // outside it cannot map into the element (a trilinear element lies in the convex hull of
  // its corners), so most candidates of a bin are passed over without a Newton inversion.
  std::vector<Vec3> box_lo_, box_hi_;
  int binIndex(const Vec3i& c) const { return c[0] + dims_[0] * (c[1] + dims_[1] * c[2]); }
  Vec3i binOf(const Vec3& p) const;
};

}  // namespace needle_sim

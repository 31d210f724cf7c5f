#pragma once
// An organ surface embedded in the hexahedral tissue mesh (immersed geometry): every vertex
// is a material point (element + trilinear weights), so the surface moves with the finite
// element field. It is what the needle punctures and what is displayed, instead of the
// grid's boundary. Vertices are located on first use: contact needs only those near the
// needle, and a mesh change (adaptivity) makes a new EmbeddedSurface.
#include <memory>
#include <vector>

#include "needle_sim/fem/embedded_point.hpp"
#include "needle_sim/geometry/triangle_mesh.hpp"

namespace needle_sim {

class EmbeddedSurface {
 public:
  EmbeddedSurface(std::shared_ptr<const TriangleMesh> surface, const HexMesh& mesh);

  const TriangleMesh& rest() const { return *surface_; }
  std::shared_ptr<const TriangleMesh> restPtr() const { return surface_; }
  const HexMesh& mesh() const { return mesh_; }
  const EmbeddedPoint& vertex(int i) const;
  Vec3 position(int i, const VecX& x) const { return vertex(i).interpolate(mesh_, x); }
  // Current positions of all vertices for nodal positions x.
  void positions(const VecX& x, std::vector<Vec3>& out) const;
  // A rest-space point as a material point; points of the surface always succeed (the
  // nearest element is taken if the point lies a rounding error outside the kept cells).
  EmbeddedPoint locate(const Vec3& rest) const;

 private:
  std::shared_ptr<const TriangleMesh> surface_;
  const HexMesh& mesh_;
  PointLocator locator_;
  mutable std::vector<EmbeddedPoint> vertex_;
  mutable std::vector<char> located_;
};

}  // namespace needle_sim

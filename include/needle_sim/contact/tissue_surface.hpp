#pragma once
// The tissue's outer surface for needle contact, in the current configuration: either the
// boundary faces of the hexahedral mesh (each split into two triangles), or, for immersed
// organ geometry, the organ's own triangles embedded in the mesh (EmbeddedSurface), so that
// the needle punctures the real surface and not the grid's.
#include <vector>

#include "needle_sim/core/types.hpp"
#include "needle_sim/fem/embedded_point.hpp"
#include "needle_sim/fem/hex_mesh.hpp"
#include "needle_sim/geometry/embedded_surface.hpp"

namespace needle_sim {

struct SurfaceHit {
  double t = 0;                 // segment parameter in [0, 1]
  Vec3 point = Vec3::Zero();    // current position of the hit
  Vec3 normal = Vec3::Zero();   // outward unit normal of the hit triangle
  EmbeddedPoint material;       // the tissue material point hit (element + natural coordinates)
};

class TissueSurface {
 public:
  explicit TissueSurface(const HexMesh& mesh);
  // The organ surface (must outlive this object).
  TissueSurface(const HexMesh& mesh, const EmbeddedSurface& organ);
  // First crossing of the segment a -> b entering the tissue (against the outward normal),
  // with node positions x (3n). False if there is none.
  bool firstEntry(const VecX& x, const Vec3& a, const Vec3& b, SurfaceHit& hit) const;
  int numFaces() const { return organ_ ? organ_->rest().numTriangles() : static_cast<int>(faces_.size()); }

 private:
  bool firstEntryOrgan(const VecX& x, const Vec3& a, const Vec3& b, SurfaceHit& hit) const;

  const HexMesh& mesh_;
  std::vector<BoundaryFace> faces_;
  const EmbeddedSurface* organ_ = nullptr;
  std::vector<Vec3> tri_lo_, tri_hi_;  // rest bounding boxes of the organ's triangles
};

}  // namespace needle_sim

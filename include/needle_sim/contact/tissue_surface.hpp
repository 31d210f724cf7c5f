#pragma once
// The tissue's outer surface for needle contact: the boundary faces of the hexahedral mesh
// in the current configuration, each split into two triangles. (Immersed organ geometry
// will provide its own surface through the same query.)
#include <vector>

#include "needle_sim/core/types.hpp"
#include "needle_sim/fem/embedded_point.hpp"
#include "needle_sim/fem/hex_mesh.hpp"

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
  // First crossing of the segment a -> b entering the tissue (against the outward normal),
  // with node positions x (3n). False if there is none.
  bool firstEntry(const VecX& x, const Vec3& a, const Vec3& b, SurfaceHit& hit) const;
  int numFaces() const { return static_cast<int>(faces_.size()); }

 private:
  const HexMesh& mesh_;
  std::vector<BoundaryFace> faces_;
};

}  // namespace needle_sim

#pragma once
// The tissue's outer surface for needle contact, in the current configuration: either the
// boundary faces of the hexahedral mesh (each split into two triangles), or, for immersed
// organ geometry, the organ's own triangles embedded in the mesh (EmbeddedSurface), so that
// the needle punctures the real surface and not the grid's.
//
// The hit's normal on the grid's faces is the surface's smoothed normal, not its facet's: the
// corner normals of the faces meeting at a node averaged (smooth shading), interpolated over
// the face. A tip pressing on soft tissue dents it into a cone of facets whose normals turn
// by up to atan(depth / cell); a facet normal then pushes the tip sideways by that slope,
// flips sign as the tip crosses the node, and the tip chattered off the node by tenths of a
// millimetre before it punctured (doc/method.md "Puncture"). The smoothed normal is the
// indentation's axis at its node and turns continuously off it. Faces turned by more than
// 60 degrees at rest (a box's edge) do not share normals: the edge stays an edge.
#include <vector>

#include "needle_sim/core/types.hpp"
#include "needle_sim/fem/embedded_point.hpp"
#include "needle_sim/fem/hex_mesh.hpp"
#include "needle_sim/geometry/embedded_surface.hpp"

namespace needle_sim {

struct SurfaceHit {
  double t = 0;                 // segment parameter in [0, 1]
  Vec3 point = Vec3::Zero();    // current position of the hit
  Vec3 normal = Vec3::Zero();   // outward unit normal there (smoothed on the grid's faces)
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

  // The smoothed outward normal at natural point weights w of face f (current positions x).
  Vec3 smoothedNormal(const VecX& x, int f, const Eigen::Matrix<double, 8, 1>& w) const;

  const HexMesh& mesh_;
  std::vector<BoundaryFace> faces_;
  // For each face corner (4 f + k): the face corners (4 g + j) at its node whose faces are
  // within the crease angle of face f at rest, itself included.
  std::vector<std::vector<int>> corner_fan_;
  const EmbeddedSurface* organ_ = nullptr;
  std::vector<Vec3> tri_lo_, tri_hi_;  // rest bounding boxes of the organ's triangles
};

}  // namespace needle_sim

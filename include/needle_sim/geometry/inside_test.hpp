#pragma once
// Inside/outside of a closed triangle surface by winding numbers along axis-parallel rays.
//
// A ray parallel to z through (x, y) crosses the surface at a sorted list of heights; a
// crossing of a triangle whose outward normal points down enters (+1), up leaves (-1). The
// running sum is the winding number of the points on the ray, and points with winding > 0
// are inside. This only needs consistently oriented triangles, so non-manifold edges and
// touching components (real segmentations) are fine. A ray whose crossings do not sum to
// zero hit a defect; it falls back to crossing parity and is counted.
//
// Volume fractions integrate the inside length exactly along z, so only the x-y directions
// are sampled: a cell's fraction is the mean over s x s rays of (inside length) / dz.
// Triangles are binned over x-y for constant-time ray queries.
#include <atomic>
#include <memory>
#include <utility>
#include <vector>

#include "needle_sim/core/types.hpp"
#include "needle_sim/geometry/triangle_mesh.hpp"

namespace needle_sim {

class InsideTest {
 public:
  explicit InsideTest(std::shared_ptr<const TriangleMesh> surface);

  const TriangleMesh& surface() const { return *surface_; }
  bool inside(const Vec3& p) const;
  // Length of {z in [z0, z1] : (x, y, z) inside}.
  double insideLength(double x, double y, double z0, double z1) const;
  // Inside volume fraction of the axis-aligned box [lo, hi] with s x s rays.
  double boxFraction(const Vec3& lo, const Vec3& hi, int s = 8) const;
  // Rays so far that hit a surface defect (crossings not summing to zero).
  long defectiveRays() const { return defective_; }

 private:
  // Sorted crossings (z, +1 entering / -1 leaving) of the z-ray through (x, y).
  void crossings(double x, double y, std::vector<std::pair<double, int>>& out) const;

  std::shared_ptr<const TriangleMesh> surface_;
  Vec3 lo_, hi_;
  double jitter_x_, jitter_y_;
  int nx_ = 1, ny_ = 1;
  double bx_ = 1, by_ = 1;
  std::vector<std::vector<int>> bins_;
  mutable std::atomic<long> defective_{0};
};

}  // namespace needle_sim

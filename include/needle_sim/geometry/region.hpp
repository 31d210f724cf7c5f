#pragma once
// A region selecting grid nodes (Dirichlet conditions, tractions): a box, a sphere, or the
// nodes within `distance` of a surface patch (the triangles of a surface whose centroids
// lie in `patch`, or all of them), as for the brainstem and optic-nerve clamps.
#include <memory>
#include <vector>

#include "needle_sim/core/types.hpp"
#include "needle_sim/geometry/triangle_mesh.hpp"

namespace needle_sim {

struct BoxRegion {
  Vec3 min = Vec3::Zero();
  Vec3 max = Vec3::Zero();
};

struct Region {
  enum class Kind { Box, Sphere, SurfaceDistance } kind = Kind::Box;
  BoxRegion box;
  Vec3 center = Vec3::Zero();
  double radius = 0;
  std::shared_ptr<const TriangleMesh> surface;  // Kind::SurfaceDistance
  std::vector<int> patch;                       // its triangles that count
  double distance = 0;
  Vec3 patch_min = Vec3::Zero(), patch_max = Vec3::Zero();  // bounds of the patch

  bool contains(const Vec3& p, double tol) const {
    switch (kind) {
      case Kind::Box:
        return ((p - box.min).array() >= -tol).all() && ((p - box.max).array() <= tol).all();
      case Kind::Sphere:
        return (p - center).norm() <= radius + tol;
      case Kind::SurfaceDistance:
        if (((p - patch_min).array() < -(distance + tol)).any() || ((p - patch_max).array() > distance + tol).any())
          return false;
        return surface->distance(p, patch) <= distance + tol;
    }
    return false;
  }
};

}  // namespace needle_sim

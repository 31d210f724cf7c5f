#include "needle_sim/contact/tissue_surface.hpp"

#include <limits>

#include "needle_sim/fem/hex8.hpp"

namespace needle_sim {

TissueSurface::TissueSurface(const HexMesh& mesh) : mesh_(mesh), faces_(mesh.boundaryFaces()) {}

bool TissueSurface::firstEntry(const VecX& x, const Vec3& a, const Vec3& b, SurfaceHit& hit) const {
  const Vec3 d = b - a;
  double best = std::numeric_limits<double>::infinity();
  for (const auto& f : faces_) {
    const Vec3 P[4] = {node3(x, f.nodes[0]), node3(x, f.nodes[1]), node3(x, f.nodes[2]), node3(x, f.nodes[3])};
    static const int tri[2][3] = {{0, 1, 2}, {0, 2, 3}};
    for (const auto& tr : tri) {
      const Vec3 &p0 = P[tr[0]], &p1 = P[tr[1]], &p2 = P[tr[2]];
      const Vec3 e1 = p1 - p0, e2 = p2 - p0;
      const Vec3 n = e1.cross(e2);
      if (!(d.dot(n) < 0)) continue;  // must enter: move against the outward normal
      // Moeller-Trumbore
      const Vec3 pv = d.cross(e2);
      const double det = e1.dot(pv);
      if (std::abs(det) < 1e-300) continue;
      const Vec3 tv = a - p0;
      const double u = tv.dot(pv) / det;
      if (u < -1e-12 || u > 1 + 1e-12) continue;
      const Vec3 qv = tv.cross(e1);
      const double v = d.dot(qv) / det;
      if (v < -1e-12 || u + v > 1 + 1e-12) continue;
      const double t = e2.dot(qv) / det;
      if (t < -1e-12 || t > 1 + 1e-12 || t >= best) continue;
      best = t;
      hit.t = t;
      hit.point = a + t * d;
      hit.normal = n.normalized();
      // Natural coordinates of the hit: the barycentric mix of the face corners' ones.
      const auto& face = hex8::kFaces[f.face];
      Vec3 xi = Vec3::Zero();
      const double bary[3] = {1 - u - v, u, v};
      for (int k = 0; k < 3; ++k) {
        const auto& sg = hex8::kCornerSigns[face[tr[k]]];
        xi += bary[k] * Vec3(sg[0], sg[1], sg[2]);
      }
      hit.material.element = f.element;
      hit.material.xi = xi;
      hit.material.weights = hex8::shape(xi);
      hit.material.rest = mesh_.elementCorners(f.element).transpose() * hit.material.weights;
    }
  }
  return std::isfinite(best);
}

}  // namespace needle_sim

#include "needle_sim/contact/tissue_surface.hpp"

#include <cmath>
#include <limits>
#include <unordered_map>

#include "needle_sim/fem/hex8.hpp"

namespace needle_sim {

namespace {
// Moeller-Trumbore for a segment a + t d entering triangle (p0, p1, p2) against its normal.
bool enters(const Vec3& a, const Vec3& d, const Vec3& p0, const Vec3& p1, const Vec3& p2, double& t, double& u,
            double& v, Vec3& n) {
  const Vec3 e1 = p1 - p0, e2 = p2 - p0;
  n = e1.cross(e2);
  if (!(d.dot(n) < 0)) return false;  // must enter: move against the outward normal
  const Vec3 pv = d.cross(e2);
  const double det = e1.dot(pv);
  if (std::abs(det) < 1e-300) return false;
  const Vec3 tv = a - p0;
  u = tv.dot(pv) / det;
  if (u < -1e-12 || u > 1 + 1e-12) return false;
  const Vec3 qv = tv.cross(e1);
  v = d.dot(qv) / det;
  if (v < -1e-12 || u + v > 1 + 1e-12) return false;
  t = e2.dot(qv) / det;
  return t >= -1e-12 && t <= 1 + 1e-12;
}

// Outward normal of quad face P at its corner k (its edges to the neighbouring corners).
Vec3 cornerNormal(const Vec3 P[4], int k) { return (P[(k + 1) % 4] - P[k]).cross(P[(k + 3) % 4] - P[k]); }
}  // namespace

TissueSurface::TissueSurface(const HexMesh& mesh) : mesh_(mesh), faces_(mesh.boundaryFaces()) {
  const int nf = static_cast<int>(faces_.size());
  std::vector<Vec3> rest_normal(nf);
  std::unordered_map<int, std::vector<int>> corners_at;  // node -> face corners 4 f + k
  for (int f = 0; f < nf; ++f) {
    const auto& q = faces_[f].nodes;
    const Vec3 P[4] = {mesh.node(q[0]), mesh.node(q[1]), mesh.node(q[2]), mesh.node(q[3])};
    rest_normal[f] = (P[2] - P[0]).cross(P[3] - P[1]).normalized();
    for (int k = 0; k < 4; ++k) corners_at[q[k]].push_back(4 * f + k);
  }
  const double crease = 0.5;  // cos 60 degrees
  corner_fan_.resize(4 * nf);
  for (int f = 0; f < nf; ++f)
    for (int k = 0; k < 4; ++k)
      for (int c : corners_at[faces_[f].nodes[k]])
        if (rest_normal[c / 4].dot(rest_normal[f]) > crease) corner_fan_[4 * f + k].push_back(c);
}

Vec3 TissueSurface::smoothedNormal(const VecX& x, int f, const hex8::Vec8& w) const {
  const auto& face = hex8::kFaces[faces_[f].face];
  Vec3 n = Vec3::Zero();
  for (int k = 0; k < 4; ++k) {
    Vec3 nk = Vec3::Zero();
    for (int c : corner_fan_[4 * f + k]) {
      const auto& q = faces_[c / 4].nodes;
      const Vec3 P[4] = {node3(x, q[0]), node3(x, q[1]), node3(x, q[2]), node3(x, q[3])};
      nk += cornerNormal(P, c % 4).normalized();
    }
    n += w[face[k]] * nk.normalized();
  }
  return n.normalized();
}

TissueSurface::TissueSurface(const HexMesh& mesh, const EmbeddedSurface& organ) : mesh_(mesh), organ_(&organ) {
  const TriangleMesh& m = organ.rest();
  tri_lo_.resize(m.numTriangles());
  tri_hi_.resize(m.numTriangles());
  for (int t = 0; t < m.numTriangles(); ++t) {
    const auto& tr = m.triangle(t);
    tri_lo_[t] = m.vertex(tr[0]).cwiseMin(m.vertex(tr[1])).cwiseMin(m.vertex(tr[2]));
    tri_hi_[t] = m.vertex(tr[0]).cwiseMax(m.vertex(tr[1])).cwiseMax(m.vertex(tr[2]));
  }
}

bool TissueSurface::firstEntryOrgan(const VecX& x, const Vec3& a, const Vec3& b, SurfaceHit& hit) const {
  // Triangles are culled in rest space: a triangle that now meets the segment was, at rest,
  // within the largest nodal displacement of it (the embedding is a convex combination).
  double umax = 0;
  for (int i = 0; i < mesh_.numNodes(); ++i) umax = std::max(umax, (node3(x, i) - mesh_.node(i)).norm());
  const Vec3 lo = a.cwiseMin(b) - Vec3::Constant(umax + 1e-12), hi = a.cwiseMax(b) + Vec3::Constant(umax + 1e-12);
  const TriangleMesh& m = organ_->rest();
  const Vec3 d = b - a;
  double best = std::numeric_limits<double>::infinity();
  for (int t = 0; t < m.numTriangles(); ++t) {
    if ((tri_hi_[t].array() < lo.array()).any() || (tri_lo_[t].array() > hi.array()).any()) continue;
    const auto& tr = m.triangle(t);
    double s, u, v;
    Vec3 n;
    if (!enters(a, d, organ_->position(tr[0], x), organ_->position(tr[1], x), organ_->position(tr[2], x), s, u, v, n))
      continue;
    if (s >= best) continue;
    best = s;
    hit.t = s;
    hit.point = a + s * d;
    hit.normal = n.normalized();
    hit.material = organ_->locate((1 - u - v) * m.vertex(tr[0]) + u * m.vertex(tr[1]) + v * m.vertex(tr[2]));
  }
  return std::isfinite(best);
}

bool TissueSurface::firstEntry(const VecX& x, const Vec3& a, const Vec3& b, SurfaceHit& hit) const {
  if (organ_) return firstEntryOrgan(x, a, b, hit);
  const Vec3 d = b - a;
  double best = std::numeric_limits<double>::infinity();
  int best_face = -1;
  for (const auto& f : faces_) {
    const Vec3 P[4] = {node3(x, f.nodes[0]), node3(x, f.nodes[1]), node3(x, f.nodes[2]), node3(x, f.nodes[3])};
    static const int tri[2][3] = {{0, 1, 2}, {0, 2, 3}};
    for (const auto& tr : tri) {
      double t, u, v;
      Vec3 n;
      if (!enters(a, d, P[tr[0]], P[tr[1]], P[tr[2]], t, u, v, n) || t >= best) continue;
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
      best_face = static_cast<int>(&f - faces_.data());
    }
  }
  if (best_face >= 0) hit.normal = smoothedNormal(x, best_face, hit.material.weights);
  return std::isfinite(best);
}

}  // namespace needle_sim

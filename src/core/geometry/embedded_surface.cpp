#include "needle_sim/geometry/embedded_surface.hpp"

namespace needle_sim {

EmbeddedSurface::EmbeddedSurface(std::shared_ptr<const TriangleMesh> surface, const HexMesh& mesh)
    : surface_(std::move(surface)), mesh_(mesh), locator_(mesh) {
  vertex_.resize(surface_->numVertices());
  located_.assign(surface_->numVertices(), 0);
}

EmbeddedPoint EmbeddedSurface::locate(const Vec3& rest) const {
  EmbeddedPoint ep;
  if (!locator_.locate(rest, ep)) locator_.locateNearest(rest, ep);
  return ep;
}

const EmbeddedPoint& EmbeddedSurface::vertex(int i) const {
  if (!located_[i]) {
    vertex_[i] = locate(surface_->vertex(i));
    located_[i] = 1;
  }
  return vertex_[i];
}

void EmbeddedSurface::positions(const VecX& x, std::vector<Vec3>& out) const {
  out.resize(surface_->numVertices());
  for (int i = 0; i < surface_->numVertices(); ++i) out[i] = position(i, x);
}

}  // namespace needle_sim

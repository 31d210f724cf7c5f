#include "needle_sim/fem/embedded_point.hpp"

#include <algorithm>
#include <cmath>

namespace needle_sim {

PointLocator::PointLocator(const HexMesh& mesh) : mesh_(mesh) {
  lo_ = mesh.boundsMin();
  hi_ = mesh.boundsMax();
  const Vec3 ext = (hi_ - lo_).cwiseMax(1e-300);
  // About one element per bin on average.
  const double n = std::max(1, mesh.numElements());
  const double vol = ext.prod();
  const double h = std::cbrt(vol / n);
  for (int d = 0; d < 3; ++d) dims_[d] = std::clamp(static_cast<int>(std::ceil(ext[d] / h)), 1, 512);
  cell_ = ext.cwiseQuotient(dims_.cast<double>());
  bins_.assign(static_cast<size_t>(dims_.prod()), {});
  box_lo_.resize(mesh.numElements());
  box_hi_.resize(mesh.numElements());
  for (int e = 0; e < mesh.numElements(); ++e) {
    const auto X = mesh.elementCorners(e);
    const Vec3 lo = X.colwise().minCoeff().transpose(), hi = X.colwise().maxCoeff().transpose();
    const Vec3 pad = Vec3::Constant(1e-7 * (hi - lo).norm());
    box_lo_[e] = lo - pad;
    box_hi_[e] = hi + pad;
    const Vec3i a = binOf(lo);
    const Vec3i b = binOf(hi);
    for (int k = a[2]; k <= b[2]; ++k)
      for (int j = a[1]; j <= b[1]; ++j)
        for (int i = a[0]; i <= b[0]; ++i) bins_[binIndex({i, j, k})].push_back(e);
  }
}

Vec3i PointLocator::binOf(const Vec3& p) const {
  Vec3i c;
  for (int d = 0; d < 3; ++d)
    c[d] = std::clamp(static_cast<int>(std::floor((p[d] - lo_[d]) / cell_[d])), 0, dims_[d] - 1);
  return c;
}

bool PointLocator::locate(const Vec3& p, EmbeddedPoint& out) const {
  const Vec3 tol = 1e-9 * cell_;
  if (((p - lo_).array() < -tol.array()).any() ||
      ((p - hi_).array() > tol.array()).any())
    return false;
  for (int e : bins_[binIndex(binOf(p))]) {
    if (((p - box_lo_[e]).array() < 0).any() || ((p - box_hi_[e]).array() > 0).any()) continue;
    Vec3 xi;
    if (!hex8::inverseMap(mesh_.elementCorners(e), p, xi)) continue;
    if (xi.cwiseAbs().maxCoeff() > 1 + 1e-9) continue;
    out.rest = p;
    out.element = e;
    out.xi = xi.cwiseMax(-1.0).cwiseMin(1.0);
    out.weights = hex8::shape(out.xi);
    return true;
  }
  return false;
}

bool PointLocator::locateNearest(const Vec3& p, EmbeddedPoint& out) const {
  const Vec3i c = binOf(p);
  double best = 1e300;
  for (int k = std::max(0, c[2] - 1); k <= std::min(dims_[2] - 1, c[2] + 1); ++k)
    for (int j = std::max(0, c[1] - 1); j <= std::min(dims_[1] - 1, c[1] + 1); ++j)
      for (int i = std::max(0, c[0] - 1); i <= std::min(dims_[0] - 1, c[0] + 1); ++i)
        for (int e : bins_[binIndex({i, j, k})]) {
          const auto X = mesh_.elementCorners(e);
          Vec3 xi;
          if (!hex8::inverseMap(X, p, xi)) continue;
          xi = xi.cwiseMax(-1.0).cwiseMin(1.0);
          const hex8::Vec8 w = hex8::shape(xi);
          const double d = (X.transpose() * w - p).norm();
          if (d < best) {
            best = d;
            out.rest = p;
            out.element = e;
            out.xi = xi;
            out.weights = w;
          }
        }
  return best < 1e300;
}

}  // namespace needle_sim

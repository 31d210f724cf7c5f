#include "needle_sim/contact/centre_line.hpp"

#include <algorithm>
#include <cmath>
#include <limits>

namespace needle_sim {

HermiteWeights hermite(double xi) {
  const double x2 = xi * xi, x3 = x2 * xi;
  return {2 * x3 - 3 * x2 + 1, x3 - 2 * x2 + xi, -2 * x3 + 3 * x2, x3 - x2,
          6 * x2 - 6 * xi,     3 * x2 - 4 * xi + 1, -6 * x2 + 6 * xi, 3 * x2 - 2 * xi};
}

CentreLinePoint centreLinePoint(const NeedleBody& nd, double s) {
  CentreLinePoint c;
  const double L0 = nd.beam().elementLength();
  const int ne = nd.beam().numElements();
  c.element = std::clamp(static_cast<int>(std::floor(s / L0)), 0, ne - 1);
  c.xi = std::clamp(s / L0 - c.element, 0.0, 1.0);
  const Vec3& a = nd.state().p[c.element];
  const Vec3& b = nd.state().p[c.element + 1];
  c.chord = (b - a).norm();
  const Vec3 ta = nd.state().q[c.element] * nd.beam().restDirection();
  const Vec3 tb = nd.state().q[c.element + 1] * nd.beam().restDirection();
  const HermiteWeights h = hermite(c.xi);
  const double l = c.chord;
  c.position = h.h00 * a + h.h10 * l * ta + h.h01 * b + h.h11 * l * tb;
  c.axis = (h.d00 * a + h.d10 * l * ta + h.d01 * b + h.d11 * l * tb).normalized();
  return c;
}

double closestArcLength(const NeedleBody& nd, const Vec3& p) {
  const double L0 = nd.beam().elementLength();
  double best = std::numeric_limits<double>::infinity(), s = 0;
  for (int e = 0; e < nd.beam().numElements(); ++e) {
    const Vec3& a = nd.state().p[e];
    const Vec3 d = nd.state().p[e + 1] - a;
    double t = std::max(0.0, d.dot(p - a) / d.squaredNorm());
    if (e + 1 < nd.beam().numElements()) t = std::min(t, 1.0);
    const double dist = (a + t * d - p).squaredNorm();
    if (dist < best) {
      best = dist;
      s = (e + t) * L0;
    }
  }
  return s;
}

Vec3 baseDrivenVelocity(const NeedleBody& nd, double xi, const Vec3& vb, const Vec3& wb) {
  const HermiteWeights h = hermite(xi);
  const double l = (nd.state().p[1] - nd.state().p[0]).norm();
  return h.h00 * vb + h.h10 * l * wb.cross(nd.state().q[0] * nd.beam().restDirection());
}

double distanceFromAxis(const NeedleBody& nd, double s, const Vec3& p) {
  const CentreLinePoint c = centreLinePoint(nd, s);
  const Vec3 d = p - c.position;
  return (d - c.axis * c.axis.dot(d)).norm();
}

}  // namespace needle_sim

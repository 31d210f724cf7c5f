#include "needle_sim/geometry/inside_test.hpp"

#include <algorithm>
#include <cmath>

namespace needle_sim {

InsideTest::InsideTest(std::shared_ptr<const TriangleMesh> surface) : surface_(std::move(surface)) {
  const TriangleMesh& m = *surface_;
  lo_ = m.boundsMin();
  hi_ = m.boundsMax();
  const double L = (hi_ - lo_).norm();
  // Rays through vertices or edges are ambiguous; an irrational-looking shift of the ray
  // (far below any length of interest) makes them as unlikely as for random rays.
  jitter_x_ = 1.2345678e-9 * L;
  jitter_y_ = 0.7654321e-9 * L;
  const double n = std::sqrt(std::max(1, m.numTriangles()));
  const double ex = std::max(hi_[0] - lo_[0], 1e-12 * L), ey = std::max(hi_[1] - lo_[1], 1e-12 * L);
  nx_ = std::clamp(static_cast<int>(std::ceil(n * std::sqrt(ex / ey))), 1, 1024);
  ny_ = std::clamp(static_cast<int>(std::ceil(n * std::sqrt(ey / ex))), 1, 1024);
  bx_ = ex / nx_;
  by_ = ey / ny_;
  bins_.assign(static_cast<size_t>(nx_) * ny_, {});
  for (int t = 0; t < m.numTriangles(); ++t) {
    const auto& tr = m.triangle(t);
    double x0 = 1e300, x1 = -1e300, y0 = 1e300, y1 = -1e300;
    for (int k : tr) {
      x0 = std::min(x0, m.vertex(k)[0]);
      x1 = std::max(x1, m.vertex(k)[0]);
      y0 = std::min(y0, m.vertex(k)[1]);
      y1 = std::max(y1, m.vertex(k)[1]);
    }
    const int i0 = std::clamp(static_cast<int>(std::floor((x0 - lo_[0]) / bx_)), 0, nx_ - 1);
    const int i1 = std::clamp(static_cast<int>(std::floor((x1 - lo_[0]) / bx_)), 0, nx_ - 1);
    const int j0 = std::clamp(static_cast<int>(std::floor((y0 - lo_[1]) / by_)), 0, ny_ - 1);
    const int j1 = std::clamp(static_cast<int>(std::floor((y1 - lo_[1]) / by_)), 0, ny_ - 1);
    for (int j = j0; j <= j1; ++j)
      for (int i = i0; i <= i1; ++i) bins_[static_cast<size_t>(j) * nx_ + i].push_back(t);
  }
}

void InsideTest::crossings(double x, double y, std::vector<std::pair<double, int>>& out) const {
  out.clear();
  x += jitter_x_;
  y += jitter_y_;
  if (x < lo_[0] || x > hi_[0] || y < lo_[1] || y > hi_[1]) return;
  const int i = std::clamp(static_cast<int>(std::floor((x - lo_[0]) / bx_)), 0, nx_ - 1);
  const int j = std::clamp(static_cast<int>(std::floor((y - lo_[1]) / by_)), 0, ny_ - 1);
  const TriangleMesh& m = *surface_;
  for (int t : bins_[static_cast<size_t>(j) * nx_ + i]) {
    const auto& tr = m.triangle(t);
    const Vec3 &a = m.vertex(tr[0]), &b = m.vertex(tr[1]), &c = m.vertex(tr[2]);
    // Signed areas in the x-y projection; all of one sign means (x, y) is inside.
    const double w0 = (b[0] - x) * (c[1] - y) - (b[1] - y) * (c[0] - x);
    const double w1 = (c[0] - x) * (a[1] - y) - (c[1] - y) * (a[0] - x);
    const double w2 = (a[0] - x) * (b[1] - y) - (a[1] - y) * (b[0] - x);
    const double area = w0 + w1 + w2;  // 2 A n_z
    if (area == 0) continue;           // vertical triangle: the ray grazes it
    if (area > 0 ? (w0 < 0 || w1 < 0 || w2 < 0) : (w0 > 0 || w1 > 0 || w2 > 0)) continue;
    const double z = (w0 * a[2] + w1 * b[2] + w2 * c[2]) / area;
    out.emplace_back(z, area < 0 ? +1 : -1);  // normal down: entering when going up
  }
  std::sort(out.begin(), out.end());
}

double InsideTest::insideLength(double x, double y, double z0, double z1) const {
  thread_local std::vector<std::pair<double, int>> cr;
  crossings(x, y, cr);
  if (cr.empty()) return 0;
  int total = 0;
  for (const auto& c : cr) total += c.second;
  const bool parity = total != 0;
  if (parity) ++defective_;
  double len = 0, start = 0;
  int w = 0;
  for (size_t k = 0; k < cr.size(); ++k) {
    const int before = w;
    w = parity ? static_cast<int>((k + 1) % 2) : w + cr[k].second;
    const bool was_in = before > 0, is_in = w > 0;
    if (!was_in && is_in) start = cr[k].first;
    if (was_in && !is_in) len += std::max(0.0, std::min(cr[k].first, z1) - std::max(start, z0));
  }
  return len;
}

bool InsideTest::inside(const Vec3& p) const {
  if ((p.array() < lo_.array()).any() || (p.array() > hi_.array()).any()) return false;
  // The winding number at p: crossings above p, counted leaving minus entering.
  thread_local std::vector<std::pair<double, int>> cr;
  int votes = 0;
  // Three slightly different rays vote, so that a single defective ray cannot decide.
  const double d = 1e-7 * (hi_ - lo_).norm();
  const double off[3][2] = {{0, 0}, {d, 0.37 * d}, {-0.61 * d, d}};
  for (const auto& o : off) {
    crossings(p[0] + o[0], p[1] + o[1], cr);
    int total = 0, above = 0, n_above = 0;
    for (const auto& c : cr) {
      total += c.second;
      if (c.first > p[2]) {
        above -= c.second;
        ++n_above;
      }
    }
    const bool in = total == 0 ? above > 0 : (n_above % 2 == 1);
    votes += in ? 1 : 0;
  }
  return votes >= 2;
}

double InsideTest::boxFraction(const Vec3& lo, const Vec3& hi, int s) const {
  const double dz = hi[2] - lo[2];
  if (hi[0] < lo_[0] || lo[0] > hi_[0] || hi[1] < lo_[1] || lo[1] > hi_[1] || hi[2] < lo_[2] || lo[2] > hi_[2])
    return 0;
  double sum = 0;
  for (int j = 0; j < s; ++j)
    for (int i = 0; i < s; ++i) {
      const double x = lo[0] + (i + 0.5) / s * (hi[0] - lo[0]);
      const double y = lo[1] + (j + 0.5) / s * (hi[1] - lo[1]);
      sum += insideLength(x, y, lo[2], hi[2]) / dz;
    }
  return std::clamp(sum / (s * s), 0.0, 1.0);
}

}  // namespace needle_sim

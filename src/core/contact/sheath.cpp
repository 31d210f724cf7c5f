#include "needle_sim/contact/sheath.hpp"

#include <algorithm>

#include "needle_sim/contact/centre_line.hpp"

namespace needle_sim {

int sheathOf(const std::vector<NeedleBody*>& needles, int n, double slack) {
  const Vec3 tip = needles[n]->tipPosition();
  for (size_t m = 0; m < needles.size(); ++m) {
    if (static_cast<int>(m) == n) continue;
    const auto& sec = needles[m]->beam().section();
    if (!(sec.inner_radius > 0) || sec.inner_radius < needles[n]->beam().section().outer_radius * (1 - 1e-9)) continue;
    const double L = needles[m]->beam().length();
    const double s = closestArcLength(*needles[m], tip);
    if (s <= 0 || s > L + slack) continue;
    if (distanceFromAxis(*needles[m], std::min(s, L), tip) <= sec.inner_radius) return static_cast<int>(m);
  }
  return -1;
}

int needleThrough(const std::vector<NeedleBody*>& needles, int from, const Vec3& p, double& s) {
  for (size_t m = 0; m < needles.size(); ++m) {
    if (static_cast<int>(m) == from) continue;
    const double sm = closestArcLength(*needles[m], p);
    if (sm <= 0 || sm >= needles[m]->beam().length()) continue;
    const double reach = needles[from]->beam().section().outer_radius + needles[m]->beam().section().outer_radius;
    if (distanceFromAxis(*needles[m], sm, p) <= reach) {
      s = sm;
      return static_cast<int>(m);
    }
  }
  return -1;
}

}  // namespace needle_sim

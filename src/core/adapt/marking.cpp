#include "needle_sim/adapt/marking.hpp"

#include <algorithm>
#include <numeric>

namespace needle_sim {

std::vector<int> MaxMarking::mark(const std::vector<double>& eta, const std::vector<char>& refinable) const {
  // The maximum is over all elements, those at max_level included: once the largest errors
  // sit in elements that may not be refined, nothing else is marked and refinement stops.
  double mx = 0;
  for (double v : eta) mx = std::max(mx, v);
  std::vector<int> out;
  if (!(mx > 0)) return out;
  for (size_t e = 0; e < eta.size(); ++e)
    if (refinable[e] && eta[e] >= theta_ * mx) out.push_back(static_cast<int>(e));
  return out;
}

std::vector<int> BulkMarking::mark(const std::vector<double>& eta, const std::vector<char>& refinable) const {
  std::vector<int> order;
  double total = 0;
  for (size_t e = 0; e < eta.size(); ++e) {
    total += eta[e] * eta[e];
    if (refinable[e]) order.push_back(static_cast<int>(e));
  }
  std::sort(order.begin(), order.end(), [&](int a, int b) { return eta[a] > eta[b]; });
  std::vector<int> out;
  double sum = 0;
  for (int e : order) {
    if (!(sum < theta_ * total)) break;
    if (!(eta[e] > 0)) break;
    out.push_back(e);
    sum += eta[e] * eta[e];
  }
  return out;
}

}  // namespace needle_sim

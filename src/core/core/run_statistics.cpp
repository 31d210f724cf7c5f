#include "needle_sim/core/run_statistics.hpp"

#include <algorithm>
#include <cmath>
#include <numeric>

namespace needle_sim {

Percentiles percentiles(std::vector<double> v) {
  Percentiles p;
  if (v.empty()) return p;
  std::sort(v.begin(), v.end());
  auto at = [&](double q) {
    const double idx = q * (v.size() - 1);
    const size_t lo = static_cast<size_t>(std::floor(idx)), hi = static_cast<size_t>(std::ceil(idx));
    return v[lo] + (idx - lo) * (v[hi] - v[lo]);
  };
  p.median = at(0.5);
  p.p95 = at(0.95);
  p.p99 = at(0.99);
  p.p999 = at(0.999);
  p.max = v.back();
  p.mean = std::accumulate(v.begin(), v.end(), 0.0) / v.size();
  return p;
}

void RunStatistics::add(double v) {
  kept_.push_back(v);
  if (window_ > 0 && kept_.size() > window_) kept_.pop_front();
  ++count_;
  sum_ += v;
  max_ = count_ == 1 ? v : std::max(max_, v);
  if (deadline_ > 0 && v > deadline_) {
    ++misses_;
    longest_run_ = std::max(longest_run_, ++run_);
  } else {
    run_ = 0;
  }
}

Percentiles RunStatistics::percentiles() const { return needle_sim::percentiles(samples()); }

void RunStatistics::clear() {
  kept_.clear();
  count_ = misses_ = run_ = longest_run_ = 0;
  sum_ = max_ = 0;
}

}  // namespace needle_sim

#pragma once
// A run's per-step figures and what they say about keeping a deadline: one accumulator for
// every report of them (the recorder's summary.json, `needle_sim bench` and `soak`, the node's
// diagnostics). Percentiles are exact over the samples kept (all of them, or the latest
// `window` for a node that runs for hours); the count, sum, maximum, deadline misses and the
// longest run of consecutive misses cover every sample added.
#include <cstddef>
#include <deque>
#include <vector>

namespace needle_sim {

struct Percentiles {
  double median = 0, p95 = 0, p99 = 0, p999 = 0, max = 0, mean = 0;
};
// Linear interpolation between order statistics; zeros for no sample.
Percentiles percentiles(std::vector<double> v);

class RunStatistics {
 public:
  // deadline: a sample above it misses it (<= 0: no deadline); window: samples kept for the
  // percentiles (0: all).
  explicit RunStatistics(double deadline = 0, size_t window = 0) : deadline_(deadline), window_(window) {}
  void add(double v);
  // Of the samples kept; the samples kept.
  Percentiles percentiles() const;
  std::vector<double> samples() const { return {kept_.begin(), kept_.end()}; }
  // Of every sample added.
  long count() const { return count_; }
  double sum() const { return sum_; }
  double max() const { return max_; }
  double deadline() const { return deadline_; }
  long misses() const { return misses_; }
  long longestMissRun() const { return longest_run_; }
  // Starts afresh (a soak's next window); the deadline and window stay.
  void clear();

 private:
  double deadline_;
  size_t window_;
  std::deque<double> kept_;
  long count_ = 0, misses_ = 0, run_ = 0, longest_run_ = 0;
  double sum_ = 0, max_ = 0;
};

}  // namespace needle_sim

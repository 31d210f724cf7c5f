#pragma once
// Shared by the rostest gtest nodes that watch ~status step by step: the last status, a
// sample of each step (the test's own Sample type, filled by the test's callback under m),
// and a guard rule's lifetime count; waiting for simulated time.
#include <gtest/gtest.h>
#include <needle_sim/SimStatus.h>

#include <mutex>
#include <string>
#include <vector>

#include "wait_for.hpp"

namespace needle_sim_test {

template <class Sample>
struct StatusRecorder {
  std::mutex m;
  std::vector<Sample> samples;
  needle_sim::SimStatus last;
  needle_sim::SimStatus status() {
    std::lock_guard<std::mutex> lk(m);
    return last;
  }
  uint64_t count(const std::string& rule) {
    uint64_t n = 0;
    if (!guardCount(status(), rule, n)) ADD_FAILURE() << "no rule " << rule;
    return n;
  }
  Sample lastSample() {
    std::lock_guard<std::mutex> lk(m);
    return samples.back();
  }
  size_t size() {
    std::lock_guard<std::mutex> lk(m);
    return samples.size();
  }
};

// Waits for d seconds of the node's simulated time (on a recorder of its ~status).
template <class Recorder>
bool simWait(Recorder& r, double d) {
  const double t0 = r.status().sim_time;
  return waitFor([&] { return r.status().sim_time >= t0 + d; }, 4 * d + 5);
}

}  // namespace needle_sim_test

#pragma once
// The output thread: every message the node sends is built and sent here, so that
// serialisation, socket writes and tf broadcasts never delay a step. Jobs run in order. The
// thread wakes every `period` while jobs come (waking it from the stepping thread per step
// cost 5-10 % of a 0.2 ms step: futex wake, and preemption on two cores) and idles after 50
// empty periods, the next job waking it; period 0: woken by every job. If it falls kMax
// jobs behind, the oldest are dropped (counted).
#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <mutex>
#include <thread>
#include "needle_sim/core/pi_mutex.hpp"

namespace needle_sim {

class OutputQueue {
 public:
  explicit OutputQueue(double period);
  ~OutputQueue();  // sends what is queued, then stops
  void post(std::function<void()> job);
  uint64_t dropped() const { return dropped_; }
  double busyMs() const { return busy_ms_; }  // time spent sending, in all
  static constexpr size_t kMax = 20000;

 private:
  void loop();
  double period_;
  PiMutex mutex_;
  std::condition_variable_any cv_;
  std::deque<std::function<void()>> queue_;
  bool stop_ = false, idle_ = false;
  std::atomic<uint64_t> dropped_{0};
  std::atomic<double> busy_ms_{0.0};
  std::thread thread_;
};

}  // namespace needle_sim

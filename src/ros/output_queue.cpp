#include "output_queue.hpp"

#include "needle_sim/core/background_priority.hpp"

#include <chrono>

namespace needle_sim {

OutputQueue::OutputQueue(double period) : period_(period) { thread_ = std::thread(&OutputQueue::loop, this); }

OutputQueue::~OutputQueue() {
  {
    std::lock_guard<PiMutex> lk(mutex_);
    stop_ = true;
  }
  cv_.notify_all();
  if (thread_.joinable()) thread_.join();
}

void OutputQueue::post(std::function<void()> job) {
  bool wake;
  {
    std::lock_guard<PiMutex> lk(mutex_);
    wake = queue_.empty() && (period_ == 0 || idle_);
    if (queue_.size() >= kMax) {
      queue_.pop_front();
      ++dropped_;
    }
    queue_.push_back(std::move(job));
  }
  if (wake) cv_.notify_one();
}

void OutputQueue::loop() {
  nameThisThread("ns_output");
  int empty = 0;
  for (;;) {
    std::deque<std::function<void()>> jobs;
    {
      std::unique_lock<PiMutex> lk(mutex_);
      auto ready = [&] { return stop_ || !queue_.empty(); };
      if (period_ > 0 && empty < 50) {
        cv_.wait_for(lk, std::chrono::duration<double>(period_), ready);
        if (!ready()) {
          ++empty;
          continue;
        }
      } else {
        idle_ = true;
        cv_.wait(lk, ready);
        idle_ = false;
      }
      empty = 0;
      if (queue_.empty() && stop_) return;
      jobs.swap(queue_);
    }
    const auto t0 = std::chrono::steady_clock::now();
    for (auto& j : jobs) j();
    busy_ms_ = busy_ms_ + std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  }
}

}  // namespace needle_sim

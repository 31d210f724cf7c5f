#include "needle_sim/sim/realtime_schedule.hpp"

#include <algorithm>
#include <cmath>

namespace needle_sim {

void RealtimeSchedule::start(double now) {
  started_ = true;
  start_ = last_tick_ = now;
  due_ = pending_ = 0;
  late_run_ = 0;
  late_times_.clear();
  skipped_times_.clear();
  done_times_.clear();
}

long RealtimeSchedule::tick(double now) {
  if (!started_) start(now);
  if (now < last_tick_) return -1;
  last_tick_ = now;
  const long due = static_cast<long>(std::floor((now - start_) / dt_ + 1e-6));
  if (due <= due_) return 0;
  if (pending_ > 0) {  // the previous period's step has not started yet
    ++skipped_;
    skipped_times_.push_back(now);
  }
  const long n = due - due_;
  pending_ = std::min<long>(pending_ + n, 100000);
  due_ = due;
  prune(now);
  return n;
}

bool RealtimeSchedule::takeStep() {
  if (pending_ <= 0) return false;
  --pending_;
  return true;
}

void RealtimeSchedule::stepDone(long step, double now) {
  ++steps_;
  done_times_.push_back(now);
  if (now > start_ + (step + 1) * dt_ + 1e-9) {
    ++late_;
    late_times_.push_back(now);
    longest_late_run_ = std::max(longest_late_run_, ++late_run_);
  } else {
    late_run_ = 0;
  }
}

void RealtimeSchedule::prune(double now) {
  while (!late_times_.empty() && late_times_.front() < now - 1.0) late_times_.pop_front();
  while (!skipped_times_.empty() && skipped_times_.front() < now - 1.0) skipped_times_.pop_front();
  while (!done_times_.empty() && done_times_.front() < now - 1.0) done_times_.pop_front();
}

RealtimeSchedule::Counts RealtimeSchedule::counts(double now) {
  prune(now);
  Counts c;
  c.steps = steps_;
  c.late = late_;
  c.skipped = skipped_;
  c.longest_late_run = longest_late_run_;
  const double window = std::clamp(now - start_, dt_, 1.0);
  c.late_per_s = late_times_.size() / window;
  c.skipped_per_s = skipped_times_.size() / window;
  // Late: of the steps done in the window (catching up, more steps than periods can end in
  // one second); skipped: of the ticks due in it.
  const double done = std::max<double>(1.0, done_times_.size());
  c.late_fraction = std::min(1.0, late_times_.size() / done);
  c.skipped_fraction = std::min(1.0, skipped_times_.size() / (window / dt_));
  return c;
}

}  // namespace needle_sim

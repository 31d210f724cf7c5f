#pragma once
// Pacing of a simulation that follows a clock (the node's timer; the wall clock, or /clock
// under simulated time): step k, which brings the state to time k dt, is due when the clock
// reaches start + k dt, and is on time if it is done before the next one is due. Each tick
// says how many steps have become due, whatever the tick rate, so a replayed clock gives the
// same steps as the recording. Two things can go wrong, counted apart (doc/ros_api.md,
// "Deadlines"):
//   - a late step: done after start + (k + 1) dt (its result arrived more than a period late);
//   - a skipped tick: a tick that found the previous period's step not yet started (the
//     stepping thread fell behind: steps then run back to back to catch up).
// Both over the node's lifetime and as rates over the last second of the clock.
#include <cstdint>
#include <deque>

namespace needle_sim {

class RealtimeSchedule {
 public:
  explicit RealtimeSchedule(double dt = 0.001) : dt_(dt) {}
  // Step 0 is the state at clock time `now` (a restart keeps the lifetime counts).
  void start(double now);
  bool started() const { return started_; }
  // A clock tick: the number of steps that became due since the last tick. A clock that
  // went back (a bag played in a loop) returns -1: the caller restarts the scene.
  long tick(double now);
  // The stepping thread takes one due step (false: none is due).
  bool takeStep();
  long pending() const { return pending_; }
  // Clock time at which the next step becomes due.
  double nextDue() const { return start_ + (due_ + 1) * dt_; }
  // Step `step` (1-based since start) finished at clock time `now`.
  void stepDone(long step, double now);
  double dt() const { return dt_; }

  struct Counts {
    uint64_t steps = 0, late = 0, skipped = 0;  // lifetime
    long longest_late_run = 0;                  // consecutive late steps, longest since start
    double late_per_s = 0, skipped_per_s = 0;   // over the last second of the clock
    double late_fraction = 0;     // of the steps done in the last second
    double skipped_fraction = 0;  // of the ticks due in the last second
  };
  Counts counts(double now);

 private:
  void prune(double now);
  double dt_;
  bool started_ = false;
  double start_ = 0, last_tick_ = 0;
  long due_ = 0, pending_ = 0;
  uint64_t steps_ = 0, late_ = 0, skipped_ = 0;
  long late_run_ = 0, longest_late_run_ = 0;
  std::deque<double> late_times_, skipped_times_, done_times_;
};

}  // namespace needle_sim

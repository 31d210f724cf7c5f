#pragma once
// Background work (a factor refresh, a mesh change's new body: doc/method.md "Time
// integration" and "Refinement and coarsening") must not delay the stepping thread: on two
// cores, with the stepping thread, a ROS node's output thread and a refresh runnable at once,
// an equal share cost steps a whole scheduler slice (about 4 ms). The background thread runs
// on the default scheduler at nice +10 (Linux: a thread's own nice value), so the stepping
// thread preempts it; it still gets a core whenever one is free (waitedForWorkNice below: 0
// when the stepping thread runs at SCHED_FIFO).
#include <pthread.h>
#include <sched.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <atomic>

namespace needle_sim {

// Names the calling thread (at most 15 characters; shown by top -H, perf, gdb), so a
// deployment can see which of the simulator's threads uses what.
inline void nameThisThread(const char* name) { (void)pthread_setname_np(pthread_self(), name); }

// The nice value of work the live loop waits for (refreshes, mesh changes): 10, so that a
// stepping thread on the default scheduler preempts it. A stepping thread at SCHED_FIFO (the
// node's ~realtime_priority) cannot be preempted by it; the node then sets 0, so that the work
// it waits for is not starved by the clients' and the outputs' threads: at 10, the DBS scene's
// refreshes (50-60 ms of work) came late during a 500 Hz client's stream and CG took up to 45
// iterations a step on the stale factor (2026-12-07).
inline std::atomic<int>& waitedForWorkNice() {
  static std::atomic<int> nice{10};
  return nice;
}

// nice: waitedForWorkNice() (by default) for work the live loop waits for; 19 for work it does
// not (the node's predictions and plans).
inline void lowerThisThreadPriority(int nice = -1) {
  if (nice < 0) nice = waitedForWorkNice();
  // A thread inherits its creator's policy: one started by a SCHED_FIFO stepping thread would
  // run at its priority, where nice means nothing.
  sched_param none{};
  (void)pthread_setschedparam(pthread_self(), SCHED_OTHER, &none);
  (void)setpriority(PRIO_PROCESS, static_cast<id_t>(syscall(SYS_gettid)), nice);
}

// For work nothing waits for (the node's predictions, plans and online estimates): SCHED_IDLE,
// so that any other thread that wakes takes its core at once (at nice 19 a woken stepping
// thread could still wait out its slice); where the policy is refused, nice 19. Threads it
// starts inherit it.
inline void idleThisThread() {
  sched_param none{};
  if (pthread_setschedparam(pthread_self(), SCHED_IDLE, &none) != 0) lowerThisThreadPriority(19);
}

}  // namespace needle_sim

#pragma once
// Whether this process may run a thread at SCHED_FIFO (root, CAP_SYS_NICE or an rtprio limit):
// the tests of real-time priority skip where it may not.
#include <pthread.h>
#include <sched.h>

#include <thread>

namespace needle_sim_test {

inline bool fifoPermitted() {
  bool ok = false;
  std::thread t([&] {
    sched_param p{};
    p.sched_priority = 10;
    ok = pthread_setschedparam(pthread_self(), SCHED_FIFO, &p) == 0;
  });
  t.join();
  return ok;
}

}  // namespace needle_sim_test

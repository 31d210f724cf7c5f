// Priority inheritance of the mutexes the node's stepping thread shares (core/pi_mutex.hpp).
// The case of 2026-12-07: the stepping thread at SCHED_FIFO waits for a lock held by a
// SCHED_IDLE thread (the wrench stream) while an ordinary thread (a client, the output thread)
// has the core. All three threads run on one CPU, so that who runs is the scheduler's choice
// alone: with inheritance the holder runs at once at its waiter's priority and lets go after
// its own 30 ms of work; without, it waits for the ordinary thread's 400 ms. The plain mutex
// is measured too: it shows that the case does make a waiter wait (the test can fail).
#include <gtest/gtest.h>
#include <pthread.h>
#include <sched.h>

#include <atomic>
#include <chrono>
#include <ctime>
#include <mutex>
#include <thread>

#include "needle_sim/core/pi_mutex.hpp"
#include "fifo_permitted.hpp"

namespace needle_sim {
namespace {

double threadCpuMs() {
  timespec ts{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return 1e3 * static_cast<double>(ts.tv_sec) + 1e-6 * static_cast<double>(ts.tv_nsec);
}

bool onCpu(int cpu) {
  cpu_set_t s;
  CPU_ZERO(&s);
  CPU_SET(cpu, &s);
  return pthread_setaffinity_np(pthread_self(), sizeof s, &s) == 0;
}

int firstCpu() {
  cpu_set_t s;
  CPU_ZERO(&s);
  if (sched_getaffinity(0, sizeof s, &s) != 0) return 0;
  for (int c = 0; c < CPU_SETSIZE; ++c)
    if (CPU_ISSET(c, &s)) return c;
  return 0;
}


// How long [ms] a SCHED_FIFO thread waits for the mutex, held by a SCHED_IDLE thread that needs
// 30 ms of CPU before it lets go, while a SCHED_OTHER thread spins for 400 ms; -1 when a
// thread could not be placed.
template <class Mutex>
double fifoWaitMs() {
  const int cpu = firstCpu();
  Mutex m;
  std::atomic<bool> locked{false}, hogging{false}, placed{true};
  std::thread holder([&] {
    sched_param none{};
    if (!onCpu(cpu) || pthread_setschedparam(pthread_self(), SCHED_IDLE, &none) != 0) placed = false;
    std::lock_guard<Mutex> lk(m);
    locked = true;
    const double t0 = threadCpuMs();
    while (threadCpuMs() - t0 < 30.0) {
    }
  });
  while (!locked) std::this_thread::sleep_for(std::chrono::milliseconds(1));
  std::thread hog([&] {
    if (!onCpu(cpu)) placed = false;
    hogging = true;
    const auto end = std::chrono::steady_clock::now() + std::chrono::milliseconds(400);
    while (std::chrono::steady_clock::now() < end) {
    }
  });
  while (!hogging) std::this_thread::sleep_for(std::chrono::milliseconds(1));
  double waited = -1;
  std::thread waiter([&] {
    sched_param p{};
    p.sched_priority = 10;
    if (!onCpu(cpu) || pthread_setschedparam(pthread_self(), SCHED_FIFO, &p) != 0) {
      placed = false;
      return;
    }
    const auto t0 = std::chrono::steady_clock::now();
    std::lock_guard<Mutex> lk(m);
    waited = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  });
  waiter.join();
  hog.join();
  holder.join();
  return placed ? waited : -1;
}

TEST(PiMutex, ItsHolderRunsAtTheWaitersPriority) {
  if (!needle_sim_test::fifoPermitted())
    GTEST_SKIP() << "SCHED_FIFO not permitted here (needs CAP_SYS_NICE or an rtprio limit)";
  const double plain = fifoWaitMs<std::mutex>();
  const double inheriting = fifoWaitMs<PiMutex>();
  ASSERT_GE(plain, 0) << "a thread could not be placed";
  ASSERT_GE(inheriting, 0) << "a thread could not be placed";
  // The plain mutex: the holder waits for the spinning thread, the waiter for the holder.
  EXPECT_GT(plain, 300.0) << "the inversion did not happen: the test cannot tell the mutexes apart";
  // Inheriting: the holder's remaining work (at most 30 ms) and two switches.
  EXPECT_LT(inheriting, 100.0) << "plain mutex " << plain << " ms";
  std::printf("fifo waiter: %.1f ms with std::mutex, %.1f ms with PiMutex\n", plain, inheriting);
}

}  // namespace
}  // namespace needle_sim

#pragma once
// A mutex with priority inheritance (PTHREAD_PRIO_INHERIT), for what the stepping thread
// shares with the node's other threads. The stepping thread may run at SCHED_FIFO
// (~realtime_priority) while the threads it hands work to run at SCHED_IDLE or nice 10
// (background_priority.hpp): with a plain mutex, a low-priority holder preempted by any
// other thread kept the stepping thread waiting, up to 47 ms on the DBS scene with a 500 Hz
// client (the wrench stream's table, 2026-12-07). With inheritance the holder runs at the
// waiter's priority until it lets go. Lockable: std::lock_guard, std::unique_lock and
// std::condition_variable_any take it.
#include <pthread.h>

#include <cerrno>
#include <system_error>

namespace needle_sim {

class PiMutex {
 public:
  PiMutex() {
    pthread_mutexattr_t a;
    pthread_mutexattr_init(&a);
    // Where the protocol is not supported the mutex is a plain one (and still a mutex).
    (void)pthread_mutexattr_setprotocol(&a, PTHREAD_PRIO_INHERIT);
    const int err = pthread_mutex_init(&m_, &a);
    pthread_mutexattr_destroy(&a);
    if (err != 0) throw std::system_error(err, std::generic_category(), "PiMutex");
  }
  ~PiMutex() { pthread_mutex_destroy(&m_); }
  PiMutex(const PiMutex&) = delete;
  PiMutex& operator=(const PiMutex&) = delete;

  void lock() {
    const int err = pthread_mutex_lock(&m_);
    if (err != 0) throw std::system_error(err, std::generic_category(), "PiMutex::lock");
  }
  bool try_lock() { return pthread_mutex_trylock(&m_) == 0; }
  void unlock() { pthread_mutex_unlock(&m_); }

 private:
  pthread_mutex_t m_;
};

}  // namespace needle_sim

#pragma once
// Number of threads of the BLAS under CHOLMOD. Debian's OpenBLAS (pthread build) spins and
// yields while waiting for work: on two cores, with other work running, this costs more than
// it gains for the per-step triangular solves, and under contention steps can stall for
// seconds. One thread gives predictable step times; more speeds up large factorisations.
// Looked up at run time, so that any BLAS works (a no-op where OpenBLAS is absent).
#include <dlfcn.h>
#include <unistd.h>

#include <algorithm>
#include <cstdlib>
#include <mutex>
#include <thread>

namespace needle_sim {

// A thread count as the tool's and the node's options give it: n > 0 as is, 0 every core (at
// most 8: OpenBLAS gains nothing beyond on these factors).
inline int threadsOrEveryCore(int n) {
  return n > 0 ? n : static_cast<int>(std::clamp(std::thread::hardware_concurrency(), 1u, 8u));
}

// Returns false when the BLAS offers no thread control. CHOLMOD's own OpenMP loops (when
// libgomp is loaded) get the same number.
inline bool setBlasThreads(int n) {
  using Fn = void (*)(int);
  if (auto omp = reinterpret_cast<Fn>(dlsym(RTLD_DEFAULT, "omp_set_num_threads"))) omp(n);
  auto f = reinterpret_cast<Fn>(dlsym(RTLD_DEFAULT, "openblas_set_num_threads"));
  if (!f) return false;
  f(n);
  return true;
}

// The BLAS's thread count now (0 when it has no thread control).
inline int blasThreads() {
  using Fn = int (*)();
  auto f = reinterpret_cast<Fn>(dlsym(RTLD_DEFAULT, "openblas_get_num_threads"));
  return f ? f() : 0;
}

// n OpenBLAS threads (n > 0) while alive, then the count there was before; n <= 0: no change.
// OpenMP's count is left alone. Scopes alive on several threads at once share the raised
// count: the first saves the count before, the last restores it. (Changing the count under
// another thread's running BLAS calls is not safe: callers that run BLAS in parallel do not
// open one.)
class ScopedBlasThreads {
 public:
  explicit ScopedBlasThreads(int n) {
    if (n <= 0 || !setter()) return;
    Shared& s = shared();
    std::lock_guard<std::mutex> lk(s.m);
    if (s.users++ == 0) {
      s.before = blasThreads();
      if (s.before > 0 && s.before != n) setter()(n);
    }
    active_ = true;
  }
  ~ScopedBlasThreads() {
    if (!active_) return;
    Shared& s = shared();
    std::lock_guard<std::mutex> lk(s.m);
    if (--s.users == 0 && s.before > 0) setter()(s.before);
  }
  ScopedBlasThreads(const ScopedBlasThreads&) = delete;
  ScopedBlasThreads& operator=(const ScopedBlasThreads&) = delete;

 private:
  struct Shared {
    std::mutex m;
    int users = 0, before = 0;
  };
  static Shared& shared() {
    static Shared s;
    return s;
  }
  using Setter = void (*)(int);
  static Setter setter() { return reinterpret_cast<Setter>(dlsym(RTLD_DEFAULT, "openblas_set_num_threads")); }
  bool active_ = false;
};

// Debian's CHOLMOD runs small OpenMP loops inside the supernodal factorisation with a
// compiled-in 4 threads that omp_set_num_threads cannot lower; on two cores their futex
// hand-offs doubled the brain-shift pre-step's time. Only OMP_THREAD_LIMIT caps them, and
// libgomp reads it once at load: a program calls this first thing in main() and is
// re-executed once with OMP_THREAD_LIMIT=1 unless the user set it. (The nodelet cannot do
// this: the launch files set the variable for its manager.)
inline void limitOpenMpThreads(char** argv) {
  if (std::getenv("OMP_THREAD_LIMIT") || std::getenv("NEEDLE_SIM_NO_REEXEC")) return;
  setenv("OMP_THREAD_LIMIT", "1", 1);
  execv("/proc/self/exe", argv);  // returns only on failure: then run as we are
}

}  // namespace needle_sim

#pragma once
// Number of threads of the BLAS under CHOLMOD. Debian's OpenBLAS (pthread build) spins and
// yields while waiting for work: on two cores, with other work running, this costs more than
// it gains for the per-step triangular solves, and under contention steps can stall for
// seconds. One thread gives predictable step times; more speeds up large factorisations.
// Looked up at run time, so that any BLAS works (a no-op where OpenBLAS is absent).
#include <dlfcn.h>

namespace needle_sim {

// Returns false when the BLAS offers no thread control.
inline bool setBlasThreads(int n) {
  using Fn = void (*)(int);
  auto f = reinterpret_cast<Fn>(dlsym(RTLD_DEFAULT, "openblas_set_num_threads"));
  if (!f) return false;
  f(n);
  return true;
}

}  // namespace needle_sim

#pragma once
// Damped motions decay towards zero through subnormal numbers, which x86 processes up to
// a hundred times slower. Real-time loops (the tool, the ROS node) flush them to zero;
// the values concerned are below 1e-308, far under any tolerance of the simulation.
#if defined(__SSE__) || defined(__x86_64__)
#include <xmmintrin.h>
#endif

namespace needle_sim {

inline void flushDenormalsToZero() {
#if defined(__SSE__) || defined(__x86_64__)
  _mm_setcsr(_mm_getcsr() | 0x8040);  // FTZ | DAZ
#endif
}

}  // namespace needle_sim

#pragma once
// Wall-clock intervals in milliseconds, for the step-time split and the benchmarks.
#include <chrono>

namespace needle_sim {

using SteadyTime = std::chrono::steady_clock::time_point;
inline SteadyTime steadyNow() { return std::chrono::steady_clock::now(); }
inline double msSince(SteadyTime t0) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
}
inline double msBetween(SteadyTime a, SteadyTime b) { return std::chrono::duration<double, std::milli>(b - a).count(); }

}  // namespace needle_sim

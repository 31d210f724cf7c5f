#pragma once
// Will this scene keep real time on this machine? Before a live loop starts (the node, and
// `needle_sim check`), a few seconds of the scene's own motion run on a deep copy of the
// simulation, paced on the wall clock as the node's stepping thread is (step k starts at
// k dt), and their step times are held against dt with the project's criteria for a live
// loop (doc/benchmarks.md, "Bounded step time"): fewer than 1 % of the steps over dt and the
// 99.9th percentile below it. A scene that will not keep up is still run; the verdict only
// says so, with the figures (doc/ros_api.md, "Pre-flight").
#include <string>
#include <vector>

#include "needle_sim/scene/scene.hpp"
#include "needle_sim/sim/simulation.hpp"

namespace needle_sim {

struct PreflightOptions {
  double wall_budget = 2.0;  // wall time at most [s] (the copy's steps and their pacing)
  bool paced = true;         // step k starts at k dt of wall time; false: back to back
};

struct PreflightResult {
  long steps = 0;          // steps timed
  long scene_steps = 0;    // the scene's steps in all
  double t_end = 0;        // simulated time reached [s]
  double duration = 0;     // the scene's duration [s]
  double dt = 0;           // [s]
  double median_ms = 0, p999_ms = 0, max_ms = 0;
  long over_dt = 0;        // steps that took longer than dt
  int max_dofs = 0;
  std::string failure;     // a step that failed (NumericalError): its message; the verdict is no
  double overShare() const { return steps > 0 ? static_cast<double>(over_dt) / steps : 0.0; }
  // The live loop's criteria: no failure, < 1 % of the steps over dt, p99.9 below dt.
  bool keepsRealTime() const { return steps > 0 && failure.empty() && overShare() < 0.01 && p999_ms < 1e3 * dt; }
  // dt over the p99.9 step: above 1, the headroom; below 1, how far short.
  double margin() const { return p999_ms > 0 ? 1e3 * dt / p999_ms : 0.0; }
  // One line: what was timed, the figures, the verdict.
  std::string summary() const;
};

// Runs `scene`'s own needle motion (the node's simulation may have dropped it for commands)
// from the state of `live` on a deep copy; `live` is not touched.
PreflightResult preflight(const Simulation& live, const Scene& scene, const PreflightOptions& options = {});

}  // namespace needle_sim

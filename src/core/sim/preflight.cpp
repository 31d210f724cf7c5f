#include "needle_sim/sim/preflight.hpp"

#include <algorithm>
#include <cstdio>
#include <thread>

#include "needle_sim/core/error.hpp"
#include "needle_sim/core/run_statistics.hpp"
#include "needle_sim/core/stopwatch.hpp"
#include "needle_sim/needle/scene_trajectory.hpp"

namespace needle_sim {

std::string PreflightResult::summary() const {
  char buf[512];
  if (steps == 0)
    return "pre-flight: no step timed" + (failure.empty() ? std::string() : " (" + failure + ")");
  std::snprintf(buf, sizeof buf,
                "pre-flight: %ld of the scene's %ld steps (to t = %.3g of %.3g s, its own motion, paced at dt %g ms, "
                "up to %d DOFs): step median %.3g ms, p99.9 %.3g ms, max %.3g ms, %ld over dt (%.1f %%): ",
                steps, scene_steps, t_end, duration, 1e3 * dt, max_dofs, median_ms, p999_ms, max_ms, over_dt,
                100 * overShare());
  std::string s = buf;
  if (!failure.empty()) return s + "a step failed (" + failure + ")";
  std::snprintf(buf, sizeof buf, "%s here, margin %.2fx (dt / p99.9)",
                keepsRealTime() ? "keeps real time" : "WILL NOT keep real time", margin());
  return s + buf;
}

PreflightResult preflight(const Simulation& live, const Scene& scene, const PreflightOptions& o) {
  PreflightResult r;
  r.dt = live.dt();
  r.scene_steps = scene.numSteps();
  r.duration = scene.duration;
  if (!(o.wall_budget > 0)) return r;
  Simulation sim(live);
  // The scene's own motion, as the CLI runs it, for a needle the live run will command (the
  // node drops it): the representative load (puncture, cutting, mesh changes).
  for (int i = 0; i < sim.numNeedles() && i < static_cast<int>(scene.needles.size()); ++i)
    if (sim.needle(i).trajectory().keyframesAfter(sim.time()).empty())
      sim.needle(i).trajectory() = sceneTrajectory(scene.needles[i]);
  RunStatistics ms(1e3 * r.dt);
  const SteadyTime start = steadyNow();
  const auto period = std::chrono::duration<double>(r.dt);
  r.max_dofs = sim.numDofs();
  for (long k = 0; sim.stepIndex() < r.scene_steps; ++k) {
    if (o.paced)
      std::this_thread::sleep_until(start + std::chrono::duration_cast<std::chrono::steady_clock::duration>(k * period));
    if (msSince(start) >= 1e3 * o.wall_budget) break;
    const SteadyTime t0 = steadyNow();
    try {
      sim.step();
    } catch (const NumericalError& e) {
      r.failure = e.what();
      break;
    }
    ms.add(msSince(t0));
    r.max_dofs = std::max(r.max_dofs, sim.numDofs());
  }
  const Percentiles p = ms.percentiles();
  r.steps = ms.count();
  r.t_end = sim.time();
  r.median_ms = p.median;
  r.p999_ms = p.p999;
  r.max_ms = ms.max();
  r.over_dt = ms.misses();
  return r;
}

}  // namespace needle_sim

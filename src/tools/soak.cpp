#include "soak.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sys/resource.h>
#include <unistd.h>

#include "needle_sim/core/error.hpp"
#include "needle_sim/io/run_recorder.hpp"
#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/sim/simulation.hpp"

using namespace needle_sim;

namespace {
// Resident set size now and at its peak [MB].
double rssMb() {
  std::ifstream f("/proc/self/statm");
  long pages = 0, resident = 0;
  f >> pages >> resident;
  return resident * static_cast<double>(sysconf(_SC_PAGESIZE)) / (1024.0 * 1024.0);
}
double peakRssMb() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return u.ru_maxrss / 1024.0;  // kB on Linux
}
}  // namespace

int soakCommand(const SoakOptions& o) {
  if (o.steps < 1) throw InputError("", "--steps", "must be >= 1");
  if (o.window < 0) throw InputError("", "--window", "must be >= 0");
  if (!(o.speed > 0) || !std::isfinite(o.speed)) throw InputError("", "--speed", "must be > 0");
  if (!(o.depth > 0) || !std::isfinite(o.depth)) throw InputError("", "--depth", "must be > 0");
  if (!(o.hold >= 0) || !std::isfinite(o.hold)) throw InputError("", "--hold", "must be >= 0");
  Scene scene = loadScene(o.scene, o.sets);
  if (scene.needles.empty()) throw InputError(o.scene, "needle", "the soak drives a needle: the scene has none");
  for (auto& n : scene.needles) n.motion.clear();  // the soak's own script drives the first needle
  Simulation sim(scene);
  BaseTrajectory& traj = sim.needle(0).trajectory();
  const BasePose start = traj.pose(0);
  BasePose deep = start;
  deep.position += o.depth * start.direction;
  const double travel = o.depth / o.speed, cycle = 2 * travel + 2 * o.hold;
  // One cycle of keyframes from time t0 (kept short: older keyframes are dropped).
  auto script = [&](double t0) {
    traj.replaceFrom(t0, 0.0, {{travel, deep}, {travel + o.hold, deep}, {2 * travel + o.hold, start}, {cycle, start}});
  };
  double next_cycle = 0;
  const long window = o.window > 0 ? o.window : std::max(1L, std::lround(cycle / scene.dt));

  std::printf("needle_sim soak: scene '%s', %ld steps of %g s, cycles of %.2f s (%.1f mm at %.1f mm/s, holds %.2f s)\n",
              scene.name.c_str(), o.steps, scene.dt, cycle, o.depth * 1e3, o.speed * 1e3, o.hold);
  std::printf("| steps | sim time s | DOFs | step median ms | step p95 ms | step max ms | RSS MB | energy J | state |\n"
              "|---|---|---|---|---|---|---|---|---|\n");
  std::ofstream csv;
  if (!o.csv.empty()) {
    csv.open(o.csv);
    if (!csv) throw std::runtime_error("cannot write " + o.csv);
    csv << "steps,time,dofs,step_median_ms,step_p95_ms,step_max_ms,rss_mb,kinetic_j,elastic_j\n";
  }
  nlohmann::json windows = nlohmann::json::array();
  std::vector<double> ms;
  ms.reserve(window);
  // RSS at the end of each full window (one cycle by default): the first cycle warms caches
  // up (cached compliance columns, the refinement forest's nodes), so growth is measured
  // from the end of the second window to the end of the last full one, at the same phase.
  std::vector<double> rss_windows;
  double rss_last = 0, max_energy = 0;
  const double rss_start = rssMb();
  using clock = std::chrono::steady_clock;
  const auto t_start = clock::now();
  for (long k = 1; k <= o.steps; ++k) {
    if (sim.time() >= next_cycle - 1e-12) {
      script(next_cycle);
      traj.dropBefore(next_cycle);
      next_cycle += cycle;
    }
    const auto t0 = clock::now();
    try {
      sim.step();
    } catch (const NumericalError& e) {
      std::fprintf(stderr, "needle_sim: numerical failure during the soak: %s\n", e.what());
      return 3;
    }
    ms.push_back(std::chrono::duration<double, std::milli>(clock::now() - t0).count());
    if (k % window == 0 || k == o.steps) {
      const auto p = percentiles(ms);
      const double rss = rssMb(), ek = sim.kineticEnergy(), ee = sim.elasticEnergy();
      if (!std::isfinite(ek) || !std::isfinite(ee)) {
        std::fprintf(stderr, "needle_sim: non-finite energy at step %ld\n", k);
        return 3;
      }
      max_energy = std::max(max_energy, ek + ee);
      if (k % window == 0) rss_windows.push_back(rss);
      rss_last = rss;
      const char* state = sim.interaction() ? toString(sim.interaction()->state(0)) : "-";
      std::printf("| %ld | %.3f | %d | %.3f | %.3f | %.2f | %.1f | %.3e | %s |\n", k, sim.time(), sim.numDofs(), p.median,
                  p.p95, p.max, rss, ek + ee, state);
      std::fflush(stdout);
      if (csv.is_open())
        csv << k << ',' << sim.time() << ',' << sim.numDofs() << ',' << p.median << ',' << p.p95 << ',' << p.max << ','
            << rss << ',' << ek << ',' << ee << '\n';
      windows.push_back({{"steps", k}, {"dofs", sim.numDofs()}, {"step_ms_median", p.median}, {"step_ms_p95", p.p95},
                         {"step_ms_max", p.max}, {"rss_mb", rss}, {"energy_j", ek + ee}});
      ms.clear();
    }
  }
  const double wall = std::chrono::duration<double>(clock::now() - t_start).count();
  const double rss_first = rss_windows.empty() ? rss_last : rss_windows.front();
  const double rss_base = rss_windows.size() > 1 ? rss_windows[1] : rss_first;
  const double rss_end = rss_windows.empty() ? rss_last : rss_windows.back();
  const double growth = rss_end - rss_base;
  std::printf("needle_sim soak: %ld steps in %.1f s, no NaN; RSS %.1f MB before the first step, %.1f / %.1f MB after "
              "the first / second window, %.1f MB after the last full window (growth since the second %+.2f MB), "
              "%.1f MB at the end, peak %.1f MB\n",
              o.steps, wall, rss_start, rss_first, rss_base, rss_end, growth, rss_last, peakRssMb());
  if (!o.json_out.empty()) {
    std::ofstream f(o.json_out);
    if (!f) throw std::runtime_error("cannot write " + o.json_out);
    f << nlohmann::json{{"scene", scene.name}, {"steps", o.steps}, {"wall_s", wall}, {"rss_start_mb", rss_start},
                        {"rss_first_window_mb", rss_first}, {"rss_second_window_mb", rss_base},
                        {"rss_last_full_window_mb", rss_end}, {"rss_growth_mb", growth}, {"rss_end_mb", rss_last}, {"rss_peak_mb", peakRssMb()},
                        {"max_energy_j", max_energy}, {"windows", windows}}
             .dump(2)
      << '\n';
  }
  if (o.max_growth_mb > 0 && growth > o.max_growth_mb) {
    std::fprintf(stderr, "needle_sim: memory grew by %.2f MB over the soak (limit %.2f MB)\n", growth, o.max_growth_mb);
    return 1;
  }
  return 0;
}

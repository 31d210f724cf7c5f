#include "soak.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <malloc.h>
#include <nlohmann/json.hpp>
#include <sys/resource.h>
#include <unistd.h>

#include "needle_sim/core/error.hpp"
#include "needle_sim/io/run_recorder.hpp"
#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/sim/observables.hpp"
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
// Bytes the program holds on the heap now [MB] (glibc: arena blocks in use plus mmap'd
// blocks). This, not RSS, tells a leak: RSS also counts freed pages glibc keeps for reuse,
// and on the adaptive phantom it swings by 2-4 MB between cycles with the phase at which
// the arena was last trimmed.
double heapMb() {
  const struct mallinfo2 m = mallinfo2();
  return static_cast<double>(m.uordblks + m.hblkhd) / (1024.0 * 1024.0);
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
  std::printf("| steps | sim time s | DOFs | step median ms | step p99.9 ms | step max ms | heap MB | RSS MB | energy J | state |\n"
              "|---|---|---|---|---|---|---|---|---|---|\n");
  std::ofstream csv;
  if (!o.csv.empty()) {
    csv.open(o.csv);
    if (!csv) throw std::runtime_error("cannot write " + o.csv);
    csv << "steps,time,dofs,step_median_ms,step_p999_ms,step_max_ms,heap_mb,rss_mb,kinetic_j,elastic_j\n";
  }
  nlohmann::json windows = nlohmann::json::array();
  RunStatistics ms(1e3 * sim.dt());  // one window's step times
  // Heap in use at the end of each full window (one cycle by default): the first cycle warms caches
  // up (cached compliance columns, the refinement forest's nodes), so growth is measured
  // from the end of the second window to the end of the last full one, at the same phase.
  std::vector<double> heap_windows;
  double rss_last = 0, heap_last = 0, max_energy = 0;
  const double rss_start = rssMb(), heap_start = heapMb();
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
    ms.add(std::chrono::duration<double, std::milli>(clock::now() - t0).count());
    if (k % window == 0 || k == o.steps) {
      const auto p = ms.percentiles();
      const double rss = rssMb(), heap = heapMb(), ek = sim.kineticEnergy(), ee = sim.elasticEnergy();
      if (!std::isfinite(ek) || !std::isfinite(ee)) {
        std::fprintf(stderr, "needle_sim: non-finite energy at step %ld\n", k);
        return 3;
      }
      max_energy = std::max(max_energy, ek + ee);
      if (k % window == 0) heap_windows.push_back(heap);
      rss_last = rss;
      heap_last = heap;
      const char* state = sim.interaction() ? toString(observe(sim).needles[0].state) : "-";
      std::printf("| %ld | %.3f | %d | %.3f | %.3f | %.2f | %.2f | %.1f | %.3e | %s |\n", k, sim.time(), sim.numDofs(),
                  p.median, p.p999, p.max, heap, rss, ek + ee, state);
      std::fflush(stdout);
      if (csv.is_open())
        csv << k << ',' << sim.time() << ',' << sim.numDofs() << ',' << p.median << ',' << p.p999 << ',' << p.max << ','
            << heap << ',' << rss << ',' << ek << ',' << ee << '\n';
      windows.push_back({{"steps", k}, {"dofs", sim.numDofs()}, {"step_ms_median", p.median}, {"step_ms_p999", p.p999},
                         {"step_ms_max", p.max}, {"heap_mb", heap}, {"rss_mb", rss}, {"energy_j", ek + ee}});
      ms.clear();
    }
  }
  const double wall = std::chrono::duration<double>(clock::now() - t_start).count();
  const double heap_first = heap_windows.empty() ? heap_last : heap_windows.front();
  const double heap_base = heap_windows.size() > 1 ? heap_windows[1] : heap_first;
  const double heap_end = heap_windows.empty() ? heap_last : heap_windows.back();
  const double growth = heap_end - heap_base;
  std::printf("needle_sim soak: %ld steps in %.1f s, no NaN; heap in use %.2f MB before the first step, %.2f / %.2f MB "
              "after the first / second window, %.2f MB after the last full window (growth since the second %+.3f MB), "
              "%.2f MB at the end; RSS %.1f MB before, %.1f MB at the end, peak %.1f MB\n",
              o.steps, wall, heap_start, heap_first, heap_base, heap_end, growth, heap_last, rss_start, rss_last,
              peakRssMb());
  if (!o.json_out.empty()) {
    std::ofstream f(o.json_out);
    if (!f) throw std::runtime_error("cannot write " + o.json_out);
    f << nlohmann::json{{"scene", scene.name}, {"steps", o.steps}, {"wall_s", wall}, {"heap_start_mb", heap_start},
                        {"heap_first_window_mb", heap_first}, {"heap_second_window_mb", heap_base},
                        {"heap_last_full_window_mb", heap_end}, {"heap_growth_mb", growth}, {"heap_end_mb", heap_last},
                        {"rss_start_mb", rss_start}, {"rss_end_mb", rss_last}, {"rss_peak_mb", peakRssMb()},
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

#include "bench.hpp"

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <iomanip>
#include <nlohmann/json.hpp>
#include <regex>
#include <thread>

#include "needle_sim/core/error.hpp"
#include "needle_sim/core/stopwatch.hpp"
#include "needle_sim/io/run_recorder.hpp"
#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/sim/simulation.hpp"

using namespace needle_sim;

namespace {

struct Timing {
  int dofs = 0;
  Percentiles total, forces, assemble, factor, solve, constraint;
  int max_points = 0;
  std::vector<std::pair<int, double>> points_ms;  // (constraint points, step ms) per timed step
  std::vector<double> constraint_ms;
  double iterations_mean = 0;
  long factorizations = 0;
  std::vector<std::vector<Vec3>> probes;  // per step, per probe
};

// steps == 0: every step of the scene, no warm-up.
Timing timeScene(const Scene& scene, int warmup, int steps) {
  if (steps == 0) {
    warmup = 0;
    steps = static_cast<int>(scene.numSteps());
  }
  Simulation sim(scene);
  Timing t;
  t.dofs = sim.numDofs();
  std::vector<double> total, forces, assemble, factor, solve;
  long iterations = 0;
  for (int k = 0; k < warmup + steps; ++k) {
    const auto t0 = steadyNow();
    const StepStats s = sim.step();
    const double ms = msSince(t0);
    std::vector<Vec3> p;
    for (int i = 0; i < sim.numProbes(); ++i) p.push_back(sim.probeDisplacement(i));
    t.probes.push_back(p);
    if (k < warmup) continue;
    total.push_back(ms);
    forces.push_back(s.forces_ms);
    assemble.push_back(s.assemble_ms);
    factor.push_back(s.factor_ms);
    solve.push_back(s.solve_ms);
    iterations += s.linear_iterations;
    t.factorizations += s.factorizations;
    t.constraint_ms.push_back(s.constraint_ms);
    t.points_ms.emplace_back(s.constraint_points, ms);
    t.max_points = std::max(t.max_points, s.constraint_points);
  }
  t.constraint = percentiles(t.constraint_ms);
  t.total = percentiles(total);
  t.forces = percentiles(forces);
  t.assemble = percentiles(assemble);
  t.factor = percentiles(factor);
  t.solve = percentiles(solve);
  t.iterations_mean = steps > 0 ? double(iterations) / steps : 0;
  return t;
}

}  // namespace

// Scenes without tissue (needles only): one row, times in microseconds.
int benchNeedles(const BenchOptions& o, const Scene& scene) {
  const int steps = std::max(o.steps, 1000);
  const Timing t = timeScene(scene, std::max(o.warmup, 10), steps);
  std::printf("needle_sim bench: %s, %d timed steps (times in microseconds)\n", o.scene.c_str(), steps);
  std::printf("| scene | needles | elements | DOFs | step median | step p99.9 | step max | forces+tangent | assembly | factor | solve |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|---|---|\n");
  int elements = 0;
  for (const auto& n : scene.needles) elements += n.elements;
  std::printf("| %s | %zu | %d | %d | %.1f | %.1f | %.1f | %.1f | %.1f | %.1f | %.1f |\n", scene.name.c_str(),
              scene.needles.size(), elements, t.dofs, 1e3 * t.total.median, 1e3 * t.total.p999, 1e3 * t.total.max,
              1e3 * t.forces.median, 1e3 * t.assemble.median, 1e3 * t.factor.median, 1e3 * t.solve.median);
  if (!o.json_out.empty()) {
    std::ofstream f(o.json_out);
    f << std::setw(2)
      << nlohmann::json{{"scene", scene.name},
                        {"dofs", t.dofs},
                        {"step_us", {{"median", 1e3 * t.total.median}, {"mean", 1e3 * t.total.mean}, {"p95", 1e3 * t.total.p95},
                                     {"p999", 1e3 * t.total.p999}, {"max", 1e3 * t.total.max}}}}
      << '\n';
  }
  return 0;
}

// Scenes with a needle-tissue interaction: whole-scene timing with the constraint phase.
int benchInteraction(const BenchOptions& o, const std::vector<std::string>& cells) {
  static const std::regex cells_re("([0-9]+)x([0-9]+)x([0-9]+)");
  std::printf("needle_sim bench: %s, %s (times in ms)\n", o.scene.c_str(),
              o.steps == 0 ? "every step of the scene" : "timed steps after warm-up");
  std::printf("| grid | DOFs | steps | step median | step p99.9 | step max | constraint phase median | constraint share "
              "| max constraint points | step median at >= 40 points | constraint share at >= 40 points |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|---|---|\n");
  nlohmann::json out = nlohmann::json::array();
  for (const auto& c : cells) {
    std::smatch m;
    if (!std::regex_match(c, m, cells_re)) throw InputError("", "--cells", "'" + c + "' is not of the form NXxNYxNZ");
    std::vector<std::string> sets = o.sets;
    sets.push_back("tissue.grid.cells=[" + m[1].str() + "," + m[2].str() + "," + m[3].str() + "]");
    const Scene scene = loadScene(o.scene, sets);
    const Timing t = timeScene(scene, o.warmup, o.steps);
    std::vector<double> many, many_c;
    double sum_total = 0, sum_c = 0;
    for (size_t k = 0; k < t.points_ms.size(); ++k) {
      sum_total += t.points_ms[k].second;
      sum_c += t.constraint_ms[k];
      if (t.points_ms[k].first >= 40) {
        many.push_back(t.points_ms[k].second);
        many_c.push_back(t.constraint_ms[k] / t.points_ms[k].second);
      }
    }
    const Percentiles pm = percentiles(many), pc = percentiles(many_c);
    std::printf("| %s | %d | %zu | %.3f | %.3f | %.3f | %.3f | %.0f %% | %d | %s | %s |\n", c.c_str(), t.dofs,
                t.points_ms.size(), t.total.median, t.total.p999, t.total.max, t.constraint.median,
                100 * sum_c / std::max(sum_total, 1e-300), t.max_points,
                many.empty() ? "-" : (std::to_string(pm.median).substr(0, 5)).c_str(),
                many.empty() ? "-" : (std::to_string(static_cast<int>(100 * pc.median)) + " %").c_str());
    std::fflush(stdout);
    out.push_back({{"grid", c},
                   {"dofs", t.dofs},
                   {"steps", t.points_ms.size()},
                   {"step_ms", {{"median", t.total.median}, {"p95", t.total.p95}, {"p999", t.total.p999}, {"max", t.total.max}}},
                   {"constraint_ms_median", t.constraint.median},
                   {"constraint_share", sum_c / std::max(sum_total, 1e-300)},
                   {"max_points", t.max_points},
                   {"step_ms_median_at_40_points", many.empty() ? 0.0 : pm.median}});
  }
  if (!o.json_out.empty()) {
    std::ofstream f(o.json_out);
    f << std::setw(2) << out << '\n';
  }
  return 0;
}

// Adaptive scenes: every step of the scene (the mesh changes as it runs); the cost of the
// adaptivity (SPR estimate, marking + refinement/coarsening, rebuilding the tissue body)
// against the whole run.
int benchAdaptive(const BenchOptions& o, const Scene& scene) {
  Simulation::Options so;
  so.target_errors = o.target_error_every > 0;
  Simulation sim(scene, so);
  if (o.target.size() == 3) sim.setTarget("bench_target", Vec3(o.target[0], o.target[1], o.target[2]));
  if (o.target_error_every > 0 && sim.numTargets() == 0)
    throw InputError(o.scene, "--target-error-every", "the scene has no target (add one with --target X Y Z)");
  const long steps = o.steps > 0 ? o.steps : scene.numSteps();
  RunStatistics total(1e3 * sim.dt());  // step times against the deadline dt
  std::vector<double> est, mark, rebuild, pass_share, goal, copy_ms;
  struct Slow {
    double ms;
    long step;
    StepStats s;
  };
  std::vector<Slow> slow;
  double sum_goal = 0;
  std::vector<double> dofs;
  double sum_total = 0, sum_adapt = 0;
  int passes = 0, changes = 0;
  const auto w0 = steadyNow();
  for (long k = 0; k < steps; ++k) {
    if (o.pace)
      std::this_thread::sleep_until(w0 + std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                                             std::chrono::duration<double>(k * sim.dt())));
    const auto t0 = steadyNow();
    const StepStats s = sim.step();
    const double ms = msSince(t0);
    if (o.slowest > 0) slow.push_back({ms, sim.stepIndex(), s});
    total.add(ms);
    dofs.push_back(sim.numDofs());
    sum_total += ms;
    sum_adapt += s.adapt_ms();
    if (o.target_error_every > 0 && sim.stepIndex() % o.target_error_every == 0) {
      // What the node's stepping thread pays for an off-thread estimate: a copy of the
      // simulation (ros_api.md, ~target_error_period). Timed apart: the estimate is timed as
      // `run --target-error` makes it, on the simulation with its current factor.
      {
        const auto c0 = steadyNow();
        const Simulation copy(sim);
        copy_ms.push_back(msSince(c0));
      }
      const auto g0 = steadyNow();
      sim.targetErrors();
      const double gms = msSince(g0);
      goal.push_back(gms);
      sum_goal += gms;
    }
    // A mesh change is counted at the step the simulation moves to the new mesh (with a
    // deferred change, adaptivity.rebuild_delay after the pass that decided it).
    if (s.mesh_changed) {
      ++changes;
      rebuild.push_back(s.rebuild_ms);
    }
    if (s.adapted) {
      ++passes;
      est.push_back(s.estimate_ms);
      mark.push_back(s.mark_refine_ms);
    }
  }
  const double wall = std::chrono::duration<double>(steadyNow() - w0).count();
  const Percentiles pt = total.percentiles(), pd = percentiles(dofs), pe = percentiles(est), pm = percentiles(mark),
                    pr = percentiles(rebuild), pg = percentiles(goal), pc = percentiles(copy_ms);
  const long misses = total.misses(), longest = total.longestMissRun();
  const AdaptationCounters ac = sim.adaptationCounters();
  std::printf("needle_sim bench: %s, %ld of the scene's %ld steps%s%s (times in ms)\n", o.scene.c_str(), steps,
              scene.numSteps(), steps < scene.numSteps() ? " (--steps 0: all of them)" : "", o.pace ? ", paced at dt" : "");
  std::printf("| scene | wall s | DOFs median | DOFs max | step median | step p99 | step p99.9 | step max | steps > dt | "
              "longest run > dt | adapt passes | mesh changes | estimate median | mark+refine median | rebuild median | "
              "adaptivity share |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
  std::printf("| %s | %.2f | %.0f | %.0f | %.3f | %.3f | %.3f | %.1f | %ld | %ld | %d | %d | %.3f | %.3f | %.3f | %.1f %% |\n",
              scene.name.c_str(), wall, pd.median, pd.max, pt.median, pt.p99, pt.p999, pt.max, misses, longest, passes,
              changes, pe.median, pm.median, pr.median, 100 * sum_adapt / std::max(sum_total, 1e-300));
  std::printf("p99.9 / median %.1f, max / median %.1f; deferred mesh changes %ld, switches that waited %ld; "
              "background passes %ld, decisions waited for %ld, passes due before a decision started after it %ld\n",
              pt.p999 / pt.median, pt.max / pt.median, ac.deferred_rebuilds, ac.rebuild_waits, ac.background_passes, ac.pass_waits,
              ac.passes_after_decision);
  if (o.slowest > 0) {
    // Where the worst steps' time went (the phases of StepStats; factor includes the needles').
    std::sort(slow.begin(), slow.end(), [](const Slow& a, const Slow& b) { return a.ms > b.ms; });
    std::printf("| slowest steps: step | ms | forces | assemble | factor (on the step / swapped in) | solve (waits) | CG it | "
                "constraints (points) | estimate | mark+refine | rebuild | mesh changed |\n"
                "|---|---|---|---|---|---|---|---|---|---|---|---|\n");
    for (size_t i = 0; i < slow.size() && i < static_cast<size_t>(o.slowest); ++i) {
      const StepStats& s = slow[i].s;
      std::printf("| %ld | %.3f | %.3f | %.3f | %.3f (%d / %d) | %.3f (%.3f) | %d | %.3f (%d) | %.3f | %.3f | %.3f | %s |\n",
                  slow[i].step, slow[i].ms, s.forces_ms, s.assemble_ms, s.factor_ms, s.factorizations,
                  s.async_factorizations, s.solve_ms, s.factor_wait_ms, s.linear_iterations,
                  s.constraint_ms, s.constraint_points, s.estimate_ms, s.mark_refine_ms, s.rebuild_ms,
                  s.mesh_changed ? "yes" : "");
    }
  }
  if (!goal.empty())
    std::printf("goal-oriented target estimate: %zu passes (every %d steps), median %.3f ms, max %.3f ms, %.1f %% of the "
                "run (steps + estimates)\n",
                goal.size(), o.target_error_every, pg.median, pg.max, 100 * sum_goal / std::max(sum_total + sum_goal, 1e-300));
  if (!copy_ms.empty())
    std::printf("copy of the simulation for it (the node's stepping thread): median %.3f ms, max %.3f ms\n", pc.median,
                pc.max);
  if (!o.json_out.empty()) {
    std::ofstream f(o.json_out);
    f << std::setw(2)
      << nlohmann::json{{"scene", scene.name},
                        {"wall_s", wall},
                        {"dofs", {{"median", pd.median}, {"max", pd.max}}},
                        {"step_ms", {{"median", pt.median}, {"p95", pt.p95}, {"p99", pt.p99}, {"p999", pt.p999},
                                     {"max", pt.max}, {"deadline_misses", misses}, {"longest_miss_run", longest}}},
                        {"paced", o.pace},
                        {"deferred_mesh_changes", ac.deferred_rebuilds},
                        {"rebuild_waits", ac.rebuild_waits},
                        {"background_passes", ac.background_passes},
                        {"pass_waits", ac.pass_waits},
                        {"passes_after_decision", ac.passes_after_decision},
                        {"target_error_ms", {{"passes", goal.size()}, {"median", pg.median}, {"max", pg.max},
                                             {"share", sum_goal / std::max(sum_total + sum_goal, 1e-300)},
                                             {"copy_median", pc.median}, {"copy_max", pc.max}}},
                        {"passes", passes},
                        {"mesh_changes", changes},
                        {"estimate_ms_median", pe.median},
                        {"mark_refine_ms_median", pm.median},
                        {"rebuild_ms_median", pr.median},
                        {"adaptivity_share", sum_adapt / std::max(sum_total, 1e-300)}}
      << '\n';
  }
  return 0;
}

int benchCommand(const BenchOptions& o) {
  static const std::regex cells_re("([0-9]+)x([0-9]+)x([0-9]+)");
  {
    std::vector<std::string> sets = o.sets;
    sets.push_back("solver.mode=dynamic");
    const Scene scene = loadScene(o.scene, sets);
    if (!scene.has_tissue) return benchNeedles(o, scene);
    if (scene.adaptivity) return benchAdaptive(o, scene);
    // The other benchmarks time fixed grids, not a scene's run: no phase to add it to.
    if (o.target_error_every > 0 || !o.target.empty())
      throw InputError(o.scene, "--target-error-every",
                       "times the target estimate on adaptive scenes only (this scene has no adaptivity section)");
    if (scene.interaction) return benchInteraction(o, o.cells);
  }
  nlohmann::json out = nlohmann::json::array();
  std::printf("needle_sim bench: %s, %d timed steps after %d warm-up steps (times in ms)\n", o.scene.c_str(), o.steps,
              o.warmup);
  std::printf("| grid | DOFs | method | step median | step p99.9 | step max | forces+RHS | assembly | factor | solve "
              "| CG it/step | factorisations | probe diff vs direct |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
  for (const auto& c : o.cells) {
    std::smatch m;
    if (!std::regex_match(c, m, cells_re)) throw InputError("", "--cells", "'" + c + "' is not of the form NXxNYxNZ");
    std::vector<std::string> sets = o.sets;
    sets.push_back("tissue.grid.cells=[" + m[1].str() + "," + m[2].str() + "," + m[3].str() + "]");
    sets.push_back("solver.mode=dynamic");
    const Scene scene = loadScene(o.scene, sets);
    std::vector<std::pair<std::string, Timing>> runs;
    runs.emplace_back(scene.solver.linear.method == LinearSolverSettings::Method::Pcg ? "pcg" : "direct",
                      timeScene(scene, o.warmup, o.steps));
    if (o.compare_direct) {
      Scene d = scene;
      d.solver.linear.method = LinearSolverSettings::Method::Direct;
      runs.emplace_back("direct", timeScene(d, o.warmup, o.steps));
    }
    // Largest probe difference over all steps, relative to the largest probe displacement.
    double diff = -1;
    if (runs.size() == 2) {
      double num = 0, den = 0;
      const auto& a = runs[0].second.probes;
      const auto& b = runs[1].second.probes;
      for (size_t k = 0; k < a.size(); ++k)
        for (size_t i = 0; i < a[k].size(); ++i) {
          num = std::max(num, (a[k][i] - b[k][i]).norm());
          den = std::max(den, b[k][i].norm());
        }
      diff = den > 0 ? num / den : 0;
    }
    for (const auto& [name, t] : runs) {
      char d[32] = "-";
      if (diff >= 0 && name != "direct") std::snprintf(d, sizeof d, "%.1e", diff);
      std::printf("| %s | %d | %s | %.3f | %.3f | %.3f | %.3f | %.3f | %.3f | %.3f | %.2f | %ld | %s |\n", c.c_str(),
                  t.dofs, name.c_str(), t.total.median, t.total.p999, t.total.max, t.forces.median,
                  t.assemble.median, t.factor.median, t.solve.median, t.iterations_mean, t.factorizations, d);
      std::fflush(stdout);
      out.push_back({{"grid", c},
                     {"dofs", t.dofs},
                     {"method", name},
                     {"step_ms", {{"median", t.total.median}, {"mean", t.total.mean}, {"p95", t.total.p95}, {"p999", t.total.p999}, {"max", t.total.max}}},
                     {"forces_ms_median", t.forces.median},
                     {"assemble_ms_median", t.assemble.median},
                     {"factor_ms_median", t.factor.median},
                     {"solve_ms_median", t.solve.median},
                     {"cg_iterations_per_step", t.iterations_mean},
                     {"factorizations", t.factorizations},
                     {"probe_relative_difference_vs_direct", diff}});
    }
  }
  if (!o.json_out.empty()) {
    std::ofstream f(o.json_out);
    f << std::setw(2) << out << '\n';
  }
  return 0;
}

#include "predict.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <nlohmann/json.hpp>

#include "needle_sim/core/error.hpp"
#include "needle_sim/io/run_recorder.hpp"
#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/command/pose_convention.hpp"
#include "needle_sim/sim/command_pipeline.hpp"
#include "needle_sim/sim/prediction.hpp"

using namespace needle_sim;

namespace {

void writeCsv(const std::string& path, const Simulation& sim, const Prediction& p) {
  std::ofstream f(path);
  if (!f) throw std::runtime_error("cannot write " + path);
  f << "t";
  for (int n = 0; n < sim.numNeedles(); ++n)
    for (const char* c : {"tip_x", "tip_y", "tip_z", "force_x", "force_y", "force_z"}) f << ',' << sim.needle(n).name() << '_' << c;
  for (int i = 0; i < sim.numTargets(); ++i)
    for (const char* c : {"_x", "_y", "_z", "_tip_distance"}) f << ',' << sim.targetName(i) << c;
  f << '\n';
  f.precision(10);
  for (const auto& s : p.samples) {
    f << s.t;
    for (size_t n = 0; n < s.tips.size(); ++n)
      for (const Vec3& v : {s.tips[n], s.base_forces[n]}) f << ',' << v[0] << ',' << v[1] << ',' << v[2];
    for (size_t i = 0; i < s.targets.size(); ++i)
      f << ',' << s.targets[i][0] << ',' << s.targets[i][1] << ',' << s.targets[i][2] << ',' << s.tip_distances[i];
    f << '\n';
  }
}

// Largest difference between two predictions at the coarse one's sample times (the fine one
// sampled at the same times).
void compare(const Prediction& coarse, const Prediction& fine, double& tip, double& target, double& force) {
  tip = target = force = 0;
  for (const auto& c : coarse.samples) {
    const auto it = std::min_element(fine.samples.begin(), fine.samples.end(), [&](const auto& a, const auto& b) {
      return std::abs(a.t - c.t) < std::abs(b.t - c.t);
    });
    for (size_t n = 0; n < c.tips.size(); ++n) {
      tip = std::max(tip, (c.tips[n] - it->tips[n]).norm());
      force = std::max(force, (c.base_forces[n] - it->base_forces[n]).norm());
    }
    for (size_t i = 0; i < c.targets.size(); ++i) target = std::max(target, (c.targets[i] - it->targets[i]).norm());
  }
}

}  // namespace

int predictCommand(const PredictOptions& o) {
  // Command-line values first: nothing is loaded for a bad one.
  if (!o.target.empty() && o.target.size() != 3) throw InputError("", "--target", "needs three values x y z");
  if (!(o.at >= 0) || !std::isfinite(o.at)) throw InputError("", "--at", "must be finite and >= 0");
  if (!std::isfinite(o.advance)) throw InputError("", "--advance", "must be finite");
  if (o.repeat < 1) throw InputError("", "--repeat", "must be >= 1");
  const Scene scene = loadScene(o.scene, o.sets);
  Simulation sim(scene);
  if (!o.target.empty()) {
    sim.setTarget("target", Vec3(o.target[0], o.target[1], o.target[2]));
  }
  const int needle = o.needle.empty() ? 0 : sim.findNeedle(o.needle);
  if (needle < 0) throw InputError(o.scene, "--needle", "no needle named '" + o.needle + "'");
  if (sim.numNeedles() == 0) throw InputError(o.scene, "needle", "the scene has no needle to plan for");
  const long live_steps = std::lround(o.at / scene.dt);
  for (long k = 0; k < live_steps; ++k) sim.step();

  // The plan: straight along the base's current axis, then held.
  const BaseTrajectory& traj = sim.needle(needle).trajectory();
  const BasePose start = traj.pose(sim.time());
  BasePose end = start;
  end.position += o.advance * start.direction;
  InsertionPlan plan;
  plan.needle = needle;
  const double over = o.over > 0 ? std::min(o.over, o.duration) : o.duration;
  plan.waypoints = {{over, end}};
  {
    // Checked as the node's ~predict checks a plan (the command pipeline with the node's
    // default limits): a plan the node would refuse is refused here too.
    CommandPipeline pipeline(sim, CommandLimits{});
    PlanPoses checked;
    const std::string why =
        pipeline.checkPlan(sim, needle, {{over, end.position, orientationOf(end, traj.rest()), 0, 0}}, checked);
    if (!why.empty()) throw InputError(o.scene, "--advance", "the command guard refuses the plan: " + why);
  }
  plan.duration = o.duration;
  plan.dt = o.dt;
  plan.sample_period = o.sample_period;

  std::vector<double> copy_ms, run_ms, total_ms;
  Prediction p;
  for (int r = 0; r < o.repeat; ++r) {
    p = predictInsertion(sim, plan);
    copy_ms.push_back(p.copy_ms);
    run_ms.push_back(p.run_ms);
    total_ms.push_back(p.copy_ms + p.run_ms);
  }
  const auto pc = percentiles(copy_ms), pr = percentiles(run_ms), pt = percentiles(total_ms);
  const auto& last = p.samples.back();
  std::printf("needle_sim predict: scene '%s' from t = %.3f s (%d dofs): needle '%s' advances %.4g m over %.3g s, "
              "%.3g s simulated at dt %.4g s (%d steps, max %d dofs)\n",
              scene.name.c_str(), sim.time(), sim.numDofs(), sim.needle(needle).name().c_str(), o.advance, over,
              o.duration, o.dt > 0 ? o.dt : scene.dt, p.steps, p.max_dofs);
  std::printf("  median over %d: total %.1f ms (copy %.2f ms, run %.1f ms); max total %.1f ms\n", o.repeat, pt.median,
              pc.median, pr.median, pt.max);
  const StepStats& t = p.totals;
  std::printf("  last run's phases [ms]: forces %.1f, assemble %.1f, factor %.1f (%d), solve %.1f (%d CG iterations), "
              "constraints %.1f (%d PGS sweeps), estimate %.1f, mark+refine %.1f, rebuild %.1f (%d mesh changes)\n",
              t.forces_ms, t.assemble_ms, t.factor_ms, t.factorizations, t.solve_ms, t.linear_iterations,
              t.constraint_ms, t.constraint_iterations, t.estimate_ms, t.mark_refine_ms, t.rebuild_ms, p.mesh_changes);
  const Vec3& tip = last.tips[needle];
  std::printf("  final tip (% .6e, % .6e, % .6e) m, force on the holder (% .3e, % .3e, % .3e) N\n", tip[0], tip[1],
              tip[2], last.base_forces[needle][0], last.base_forces[needle][1], last.base_forces[needle][2]);
  std::printf("  largest tip speed %.4g m/s over one step, at %.4g s (sim/tip_speed.hpp; the node's ~predict reports "
              "the same)\n", p.max_tip_speed, p.max_tip_speed_t);
  for (int i = 0; i < sim.numTargets(); ++i)
    std::printf("  target %-8s final (% .6e, % .6e, % .6e) m, tip distance %.6e m\n", sim.targetName(i).c_str(),
                last.targets[i][0], last.targets[i][1], last.targets[i][2], last.tip_distances[i]);
  nlohmann::json j;
  j["scene"] = scene.name;
  j["at"] = sim.time();
  j["duration"] = o.duration;
  j["dt"] = o.dt > 0 ? o.dt : scene.dt;
  j["steps"] = p.steps;
  j["max_dofs"] = p.max_dofs;
  j["repeat"] = o.repeat;
  j["total_ms_median"] = pt.median;
  j["copy_ms_median"] = pc.median;
  j["run_ms_median"] = pr.median;
  j["final_tip"] = {tip[0], tip[1], tip[2]};
  j["max_tip_speed"] = p.max_tip_speed;
  j["max_tip_speed_t"] = p.max_tip_speed_t;
  if (o.compare && (o.dt > 0 && o.dt != scene.dt)) {
    InsertionPlan fine = plan;
    fine.dt = 0;
    const Prediction f = predictInsertion(sim, fine);
    double dtip, dtarget, dforce;
    compare(p, f, dtip, dtarget, dforce);
    std::printf("  against dt %.4g s (%d steps, %.1f ms): max difference tip %.3e m, target %.3e m, force %.3e N "
                "(max force %.3e N)\n",
                scene.dt, f.steps, f.copy_ms + f.run_ms, dtip, dtarget, dforce,
                std::max_element(f.samples.begin(), f.samples.end(), [&](const auto& a, const auto& b) {
                  return a.base_forces[needle].norm() < b.base_forces[needle].norm();
                })->base_forces[needle].norm());
    j["compare"] = {{"dt", scene.dt}, {"steps", f.steps}, {"ms", f.copy_ms + f.run_ms}, {"tip_m", dtip},
                    {"target_m", dtarget}, {"force_n", dforce}};
  }
  if (!o.csv.empty()) writeCsv(o.csv, sim, p);
  if (!o.json_out.empty()) {
    std::ofstream f(o.json_out);
    if (!f) throw std::runtime_error("cannot write " + o.json_out);
    f << j.dump(2) << '\n';
  }
  return 0;
}

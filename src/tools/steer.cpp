#include "steer.hpp"

#include <cmath>
#include <cstdio>
#include <fstream>
#include <nlohmann/json.hpp>

#include "needle_sim/core/error.hpp"
#include "needle_sim/command/pose_convention.hpp"
#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/sim/command_pipeline.hpp"
#include "needle_sim/sim/observables.hpp"
#include "needle_sim/steer/steering_planner.hpp"

using namespace needle_sim;

int steerCommand(const SteerOptions& o) {
  if (o.target.size() != 3) throw InputError("", "--target", "needs three values x y z [m]");
  const Scene scene = loadScene(o.scene, o.sets);
  Simulation sim(scene);
  SteeringRequest req;
  if (!o.needle.empty()) {
    req.needle = sim.findNeedle(o.needle);
    if (req.needle < 0) throw InputError(o.scene, "--needle", "no needle named '" + o.needle + "'");
  }
  if (sim.numNeedles() == 0) throw InputError(o.scene, "needle", "the scene has no needle to steer");
  // The guard the live run goes through: the node's defaults, or the limits given.
  CommandLimits limits;
  limits.max_speed = o.max_speed;
  limits.max_angular_speed = o.max_angular_speed;
  CommandPipeline pipeline(sim, limits);  // (refuses limits out of range, naming them)
  req.target = Vec3(o.target[0], o.target[1], o.target[2]);
  req.speed = o.speed;
  req.roll_rate = o.roll_rate > 0 ? o.roll_rate : std::min(limits.max_angular_speed, M_PI);
  req.dt = o.dt;
  req.tolerance = o.tolerance;
  req.max_predictions = o.max_predictions;
  const SteeringPlan plan = planSteering(sim, req);

  std::printf("steer: %zu predictions in %.2f s; fitted curvature %.4g 1/m\n", plan.iterations.size(), plan.ms / 1e3,
              plan.kappa);
  for (size_t i = 0; i < plan.iterations.size(); ++i) {
    const SteeringIterate& it = plan.iterations[i];
    std::printf("  %zu: roll %8.4f rad, flip at %7.3f mm, advance %7.3f mm -> distance %7.3f mm (%.2f s, %d steps%s)\n",
                i + 1, it.roll, 1e3 * std::min(it.flip_depth, it.advance), 1e3 * it.advance, 1e3 * it.distance,
                it.ms / 1e3, it.steps_run,
                it.resumed_at > 0 ? (" from " + std::to_string(it.resumed_at).substr(0, 5) + " s").c_str() : "");
  }
  std::printf("plan: roll %.4f rad, %s, advance %.3f mm; predicted tip (%.6f, %.6f, %.6f) m, %.3f mm from the target%s\n",
              plan.roll,
              plan.flip_depth < plan.advance ? ("flip by pi at " + std::to_string(1e3 * plan.flip_depth) + " mm").c_str()
                                             : "no flip",
              1e3 * plan.advance, plan.tip.x(), plan.tip.y(), plan.tip.z(), 1e3 * plan.distance,
              plan.reached ? "" : " (not within the tolerance)");
  nlohmann::json j;
  j["target"] = o.target;
  j["reached"] = plan.reached;
  j["roll"] = plan.roll;
  j["flip_depth"] = plan.flip_depth < plan.advance ? nlohmann::json(plan.flip_depth) : nlohmann::json(nullptr);
  j["advance"] = plan.advance;
  j["kappa"] = plan.kappa;
  j["predicted_tip"] = {plan.tip.x(), plan.tip.y(), plan.tip.z()};
  j["predicted_distance"] = plan.distance;
  j["plan_s"] = plan.ms / 1e3;
  for (const auto& [t, p] : plan.plan.waypoints)
    j["waypoints"].push_back({{"t", t}, {"position", {p.position.x(), p.position.y(), p.position.z()}}, {"roll", p.roll}});
  for (const SteeringIterate& it : plan.iterations)
    j["iterations"].push_back({{"roll", it.roll}, {"flip_depth", it.flip_depth}, {"advance", it.advance},
                               {"distance", it.distance}, {"seconds", it.ms / 1e3},
                               {"steps_run", it.steps_run}, {"resumed_at", it.resumed_at}});
  if (o.live) {
    // The plan as a command, through the pipeline as the node's ~steer executes it, then the
    // live simulation at the scene's own time step (the predictions may have used a coarser one).
    const BasePose& rest = sim.needle(req.needle).trajectory().rest();
    const double now = sim.time(), end = plan.plan.waypoints.back().first;
    CommandPipeline::Plan command{req.needle, {}, "steer --live", nullptr, ""};
    for (const auto& [t, pose] : plan.plan.waypoints)
      command.waypoints.push_back({t, pose.position, orientationOf(pose, rest), 0, 0});
    std::string refused;
    command.done = [&](const std::string& why) { refused = why; };
    pipeline.submitPlan(std::move(command));
    pipeline.beforeStep(sim);
    if (!refused.empty()) {
      std::printf("live: not run: the command guard refuses the plan: %s\n", refused.c_str());
      j["live_refused"] = refused;
    } else {
      while (sim.time() - now < end - 1e-9 * sim.dt()) sim.step();
      const Vec3 tip = observe(sim).needles[req.needle].tip;
      const double dist = (tip - req.target).norm(), off = (tip - plan.tip).norm();
      std::printf("live: tip (%.6f, %.6f, %.6f) m, %.3f mm from the target, %.3f mm from the prediction\n", tip.x(),
                  tip.y(), tip.z(), 1e3 * dist, 1e3 * off);
      j["live_tip"] = {tip.x(), tip.y(), tip.z()};
      j["live_distance"] = dist;
      j["live_vs_predicted"] = off;
    }
  }
  if (!o.json_out.empty()) {
    std::ofstream f(o.json_out);
    if (!f) throw std::runtime_error("cannot write " + o.json_out);
    f << j.dump(2) << '\n';
  }
  return plan.reached && (!o.live || !j.contains("live_refused")) ? 0 : 1;
}

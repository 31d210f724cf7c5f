// SimulatorRos: ~steer (needle_sim/SteerToTarget), on the predictions' callback thread. The
// core's steering planner (steer/steering_planner.hpp) shoots a roll-flip plan on copies of
// the state of now; this layer converts the request's frame and the plan, and, when asked,
// hands the plan to the stepping thread like a command trajectory.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>

#include "conversions.hpp"
#include "needle_sim/command/pose_convention.hpp"
#include "needle_sim/core/error.hpp"
#include "needle_sim/ros/simulator_ros.hpp"
#include "needle_sim/steer/steering_planner.hpp"
#include "node_parameters.hpp"

namespace needle_sim {

bool SimulatorRos::onSteer(needle_sim::SteerToTarget::Request& req, needle_sim::SteerToTarget::Response& res,
                           const std::string& caller) {
  const auto w0 = ros::WallTime::now();
  const long generation = ++predict_generation_;
  const PredictionBudget budget = predictionBudget(generation);  // from the request's arrival
  std::lock_guard<std::mutex> turn(predict_turn_mutex_);  // one at a time; superseded: stops at once
  const double nan = std::numeric_limits<double>::quiet_NaN();
  res.success = res.reached = res.executed = false;
  res.roll = res.flip_depth = res.advance = res.predicted_distance = res.curvature = nan;
  auto refuse = [&](const std::string& why) {
    res.message = why;
    ROS_WARN("needle_sim: steer refused: %s", why.c_str());
    return true;
  };
  const int needle = needleIndex(req.needle);
  if (needle < 0) return refuse("needle: no needle named '" + req.needle + "'");
  SteeringRequest q;
  q.budget = budget;  // for all its predictions together
  q.needle = needle;
  auto number = [&](const char* key, double v, double fallback, double& out) {
    if (!std::isfinite(v) || v < 0) return std::string(key) + ": must be finite and >= 0 (0: the default)";
    out = v > 0 ? v : fallback;
    return std::string();
  };
  // The plan must pass the command guard: by default it turns at the guard's angular limit.
  const CommandLimits lim = guard().limits();
  for (const std::string& why : {number("speed", req.speed, std::min(q.speed, lim.max_speed), q.speed),
                                 number("roll_rate", req.roll_rate, std::min(q.roll_rate, lim.max_angular_speed),
                                        q.roll_rate),
                                 number("dt", req.dt, params_->predict_dt, q.dt),
                                 number("tolerance", req.tolerance, q.tolerance, q.tolerance)})
    if (!why.empty()) return refuse(why);
  char buf[256];
  if (q.speed > lim.max_speed) {
    std::snprintf(buf, sizeof buf, "speed: %g m/s is faster than ~max_speed = %g m/s", q.speed, lim.max_speed);
    return refuse(buf);
  }
  if (q.roll_rate > lim.max_angular_speed) {
    std::snprintf(buf, sizeof buf, "roll_rate: %g rad/s is faster than ~max_angular_speed = %g rad/s", q.roll_rate,
                  lim.max_angular_speed);
    return refuse(buf);
  }
  if (q.dt > predict_max_dt_) {
    std::snprintf(buf, sizeof buf, "dt: %g s is coarser than ~predict_max_dt = %g s (as for ~predict)", q.dt,
                  predict_max_dt_);
    return refuse(buf);
  }
  if (req.max_predictions < 0) return refuse("max_predictions: must be >= 0 (0: the default)");
  if (req.max_predictions > 0) q.max_predictions = req.max_predictions;  // (the planner refuses > 100)
  q.max_steps = params_->predict_max_steps;  // as ~predict: a request cannot hold the thread for hours
  Rigid to_tissue;
  if (!toTissue(req.target.header.frame_id, req.target.header.stamp, "~steer", to_tissue))
    return refuse(frameRefusal("target", req.target.header.frame_id));
  q.target = to_tissue.apply(fromPoint(req.target.point));
  std::unique_ptr<Simulation> snapshot;
  BasePose rest;
  {
    // The state of now, copied under the lock; the planning runs without it.
    std::lock_guard<PiMutex> lk(sim_mutex_);
    if (!failure_.empty()) return refuse("the simulation has failed (" + failure_ + "); call ~reset first");
    snapshot = std::make_unique<Simulation>(*sim_);
    rest = sim_->needle(needle).trajectory().rest();
  }
  SteeringPlan plan;
  try {
    plan = planSteering(*snapshot, q);
  } catch (const InputError& e) {
    return refuse(e.what());
  } catch (const NumericalError& e) {
    res.message = std::string("a predicted run failed: ") + e.what();
    predictionDone((ros::WallTime::now() - w0).toSec(), "failed");
    ROS_WARN("needle_sim: steer: %s", res.message.c_str());
    return true;
  } catch (const PredictionStopped& e) {
    res.message = std::string("planning stopped: a prediction was ") + e.what();
    const bool preempted = superseded(generation);
    if (preempted) res.message += " (preempted: a newer ~predict or ~steer request arrived; ~predict_preempt)";
    predictionDone((ros::WallTime::now() - w0).toSec(),
                   preempted ? "preempted" : res.message.find("cancelled") != std::string::npos ? "cancelled" : "stopped");
    ROS_WARN("needle_sim: steer: %s", res.message.c_str());
    return true;
  }
  predictionDone((ros::WallTime::now() - w0).toSec(), "ok");
  res.plan.header.frame_id = params_->tissue_frame;
  res.plan.header.stamp = ros::Time::now();
  std::vector<PlanWaypoint> waypoints;
  for (const auto& [t, p] : plan.plan.waypoints) {
    needle_sim::NeedleWaypoint w;
    w.time_from_start = ros::Duration(t);
    const Eigen::Quaterniond o = orientationOf(p, rest);
    w.pose = toPose(p.position, o);
    res.plan.waypoints.push_back(w);
    PlanWaypoint x;
    x.time = t;
    x.position = p.position;
    x.orientation = o;
    waypoints.push_back(x);
  }
  res.roll = plan.roll;
  res.flip_depth = plan.flip_depth < plan.advance ? plan.flip_depth : nan;
  res.advance = plan.advance;
  res.predicted_tip = toPoint(plan.tip);
  res.predicted_distance = plan.distance;
  res.curvature = plan.kappa;
  for (const SteeringIterate& it : plan.iterations) res.iteration_distances.push_back(it.distance);
  res.reached = plan.reached;
  res.success = true;
  if (req.execute && plan.reached) {
    // The caller's command (rule owner): refused now if another source commands the needle
    // (and again by the stepping thread when it takes the plan).
    std::string why;
    bool free;
    {
      std::lock_guard<PiMutex> lk(sim_mutex_);
      free = guard().mayCommand(needle, caller, sim_->time(), why);
    }
    if (!free) {
      warnRule(GuardRule::Owner, "~steer from " + caller, why);
      res.message = "the plan is not executed: owner: " + why;
    } else {
      queuePlan({needle, std::move(waypoints), "~steer from " + caller, {}, caller});
      res.executed = true;
    }
  }
  res.compute_time = (ros::WallTime::now() - w0).toSec();
  std::snprintf(buf, sizeof buf, "%s: %zu predictions in %.2f s, predicted tip %.3f mm from the target%s",
                plan.reached ? "reached" : "not reached within the tolerance", plan.iterations.size(),
                res.compute_time, 1e3 * plan.distance, res.executed ? "; the plan runs" : "");
  res.message = res.message.empty() ? std::string(buf) : std::string(buf) + "; " + res.message;
  return true;
}

}  // namespace needle_sim

// SimulatorRos services: ~reset, ~set_target, ~predict (on its own callback thread: the
// prediction runs on a copy of the simulation, the live run goes on meanwhile).
#include <needle_sim/SimStatus.h>

#include <pthread.h>
#include <sched.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <limits>

#include "conversions.hpp"
#include "node_assimilation.hpp"
#include "display_outputs.hpp"
#include "insert_action.hpp"
#include "needle_sim/core/background_priority.hpp"
#include "needle_sim/core/error.hpp"
#include "needle_sim/ros/simulator_ros.hpp"
#include "needle_sim/sim/prediction.hpp"
#include "node_parameters.hpp"

namespace needle_sim {

int SimulatorRos::needleIndex(const std::string& name) const {
  if (name.empty()) return scene_.needles.empty() ? -1 : 0;
  for (int i = 0; i < static_cast<int>(scene_.needles.size()); ++i)
    if (scene_.needles[i].name == name) return i;
  return -1;
}

std::string SimulatorRos::frameRefusal(const std::string& field, const std::string& frame) const {
  if (frame.empty()) return field + ": empty frame_id (rule empty_frame: set it, or ~allow_empty_frame)";
  return field + ": frame '" + frame + "' has no transform to '" + params_->tissue_frame + "' (rule frame)";
}

bool SimulatorRos::onReset(std_srvs::Trigger::Request&, std_srvs::Trigger::Response& res) {
  std::lock_guard<PiMutex> lk(sim_mutex_);
  try {
    load();
  } catch (const std::exception& e) {
    res.success = false;
    res.message = e.what();
    return true;
  }
  if (action_) action_->abort("the simulation was reset");
  if (assimilation_) assimilation_->restart();  // a new session: its measurements start again
  ++predict_epoch_;  // a prediction of the state before is cancelled
  // The command guard's and the schedule's counters are kept: they count over the node's life.
  res.success = true;
  res.message = "reset to the initial state of scene '" + scene_.name + "'";
  return true;
}

bool SimulatorRos::onSetTarget(needle_sim::SetTarget::Request& req, needle_sim::SetTarget::Response& res) {
  std::lock_guard<PiMutex> lk(sim_mutex_);
  try {
    primary_target_ = sim_->setTarget(req.name, fromPoint(req.point));
    names_ = std::make_shared<const ObservableNames>(observableNames(*sim_));
    // The estimator's refits set it too: their prediction covers it.
    if (assimilation_) assimilation_->setTarget(req.name, fromPoint(req.point));
  } catch (const std::exception& e) {
    res.success = false;
    res.message = e.what();
    ROS_WARN("needle_sim: set_target rejected: %s", e.what());
    return true;
  }
  res.success = true;
  res.message = "target '" + req.name + "' set";
  return true;
}

bool SimulatorRos::superseded(long generation) const {
  return params_->predict_preempt && predict_generation_.load() != generation;
}

PredictionBudget SimulatorRos::predictionBudget(long generation) {
  // The predictions' thread (its own spinner) gives way to every other thread of the node:
  // the live loop never waits for a prediction (idleThisThread: SCHED_IDLE).
  static thread_local bool lowered = false;
  if (!lowered) {
    nameThisThread("ns_predict");
    idleThisThread();
    lowered = true;
  }
  PredictionBudget b;
  if (params_->predict_max_wall > 0) {
    b.deadline = std::chrono::steady_clock::now() + std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                                                        std::chrono::duration<double>(params_->predict_max_wall));
    char buf[64];
    std::snprintf(buf, sizeof buf, "~predict_max_wall = %g s", params_->predict_max_wall);
    b.deadline_name = buf;
  }
  const long epoch = predict_epoch_.load();
  // ~reset and the node's end cancel it; so does a newer request (~predict_preempt): a
  // planner wants the answer to its latest question, not to one it has given up on.
  b.cancelled = [this, epoch, generation] { return predict_epoch_.load() != epoch || superseded(generation); };
  return b;
}

void SimulatorRos::predictionDone(double wall_s, const char* outcome) {
  std::lock_guard<std::mutex> lk(predict_cost_mutex_);
  PredictionCost& c = predict_cost_;
  ++c.requests;
  if (std::string(outcome) == "stopped") ++c.stopped;
  if (std::string(outcome) == "cancelled") ++c.cancelled;
  if (std::string(outcome) == "preempted") ++c.preempted;
  c.last_s = wall_s;
  c.max_s = std::max(c.max_s, wall_s);
  c.total_s += wall_s;
}

bool SimulatorRos::onPredict(needle_sim::PredictInsertion::Request& req, needle_sim::PredictInsertion::Response& res) {
  const auto w0 = ros::WallTime::now();
  const long generation = ++predict_generation_;
  const PredictionBudget budget = predictionBudget(generation);  // from the request's arrival
  std::lock_guard<std::mutex> turn(predict_turn_mutex_);  // one at a time; superseded: stops at once
  res.success = false;
  res.final_target_tip_distance = std::numeric_limits<double>::quiet_NaN();
  res.max_tip_speed = res.max_tip_speed_time = std::numeric_limits<double>::quiet_NaN();
  auto refuse = [&](const std::string& why) {
    res.message = why;
    ROS_WARN("needle_sim: predict refused: %s", why.c_str());
    return true;
  };
  const int needle = needleIndex(req.needle);
  if (needle < 0) return refuse("needle: no needle named '" + req.needle + "'");
  if (!std::isfinite(req.dt) || req.dt < 0) return refuse("dt: must be finite and >= 0");
  if (req.dt > predict_max_dt_)
    return refuse("dt: " + std::to_string(req.dt) + " s is coarser than ~predict_max_dt = " +
                  std::to_string(predict_max_dt_) + " s (by default 10 times the scene's dt " +
                  std::to_string(scene_.dt) + " s, or ~predict_dt if larger): the holder force and the tip's track "
                  "mean nothing at such a step");
  if (!std::isfinite(req.sample_period) || req.sample_period < 0) return refuse("sample_period: must be finite and >= 0");
  InsertionPlan plan;
  plan.needle = needle;
  plan.duration = req.duration;
  plan.dt = req.dt > 0 ? req.dt : params_->predict_dt;
  plan.sample_period = req.sample_period > 0 ? req.sample_period : params_->predict_sample_period;
  plan.target_error = params_->target_error_period > 0;
  Rigid to_tissue;
  if (!toTissue(req.trajectory.header.frame_id, req.trajectory.header.stamp, "~predict", to_tissue))
    return refuse(frameRefusal("trajectory", req.trajectory.header.frame_id));
  std::unique_ptr<Simulation> snapshot;
  int target = -1;
  {
    // The state of now, copied under the lock (about a millisecond); the prediction runs
    // without it, so the live simulation goes on meanwhile.
    std::lock_guard<PiMutex> lk(sim_mutex_);
    if (!failure_.empty()) return refuse("the simulation has failed (" + failure_ + "); call ~reset first");
    target = req.target.empty() ? (sim_->numTargets() > 0 ? std::min(primary_target_, sim_->numTargets() - 1) : -1)
                                : sim_->findTarget(req.target);
    if (!req.target.empty() && target < 0) return refuse("target: no target named '" + req.target + "'");
    const std::string why = pipeline_->checkPlan(*sim_, needle, toWaypoints(req.trajectory, to_tissue), plan.waypoints);
    if (!why.empty()) return refuse("trajectory: " + why);
    snapshot = std::make_unique<Simulation>(*sim_);
  }
  Prediction p;
  try {
    p = predictInsertion(*snapshot, plan, params_->predict_max_steps, {}, budget);
  } catch (const InputError& e) {
    return refuse(e.what());
  } catch (const NumericalError& e) {
    res.message = std::string("the predicted run failed: ") + e.what();
    res.compute_time = (ros::WallTime::now() - w0).toSec();
    predictionDone(res.compute_time, "failed");
    ROS_WARN("needle_sim: predict: %s", res.message.c_str());
    return true;
  } catch (const PredictionStopped& e) {
    res.message = std::string("the prediction was ") + e.what();
    const bool preempted = superseded(generation);
    if (preempted) res.message += " (preempted: a newer ~predict or ~steer request arrived; ~predict_preempt)";
    res.compute_time = (ros::WallTime::now() - w0).toSec();
    predictionDone(res.compute_time, preempted ? "preempted"
                                                : res.message.find("cancelled") != std::string::npos ? "cancelled"
                                                                                                     : "stopped");
    ROS_WARN("needle_sim: predict: %s", res.message.c_str());
    return true;
  }
  for (const auto& s : p.samples) {
    res.time.push_back(s.t);
    res.tip_position.push_back(toPoint(s.tips[needle]));
    res.base_force.push_back(toVector(s.base_forces[needle]));
    if (target >= 0) {
      res.target_position.push_back(toPoint(s.targets[target]));
      res.target_tip_distance.push_back(s.tip_distances[target]);
      if (plan.target_error) res.target_error_bound.push_back(s.target_error_bounds[target]);
    }
  }
  if (target >= 0) res.final_target_tip_distance = res.target_tip_distance.back();
  res.max_tip_speed = p.max_tip_speed;
  res.max_tip_speed_time = p.max_tip_speed_t;
  res.steps = p.steps;
  res.max_dofs = p.max_dofs;
  res.compute_time = (ros::WallTime::now() - w0).toSec();
  predictionDone(res.compute_time, "ok");
  res.success = true;
  char buf[200];
  std::snprintf(buf, sizeof buf, "predicted %.3g s in %d steps of %.3g s (%.3f s wall); largest tip speed %.3g m/s at %.3g s",
                p.samples.back().t, p.steps, plan.dt, res.compute_time, p.max_tip_speed, p.max_tip_speed_t);
  res.message = buf;
  return true;
}

}  // namespace needle_sim

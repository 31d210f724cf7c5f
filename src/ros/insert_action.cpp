#include "insert_action.hpp"

#include <algorithm>
#include <cmath>
#include <limits>

#include "conversions.hpp"
#include "needle_sim/command/pose_convention.hpp"
#include "needle_sim/ros/simulator_ros.hpp"
#include "output_queue.hpp"

namespace needle_sim {

InsertAction::InsertAction(SimulatorRos& node, ros::NodeHandle& pnh, double default_speed)
    : node_(node),
      default_speed_(default_speed),
      server_(pnh, "insert", [this](Server::GoalHandle gh) { onGoal(gh); },
              [this](Server::GoalHandle gh) { onCancel(gh); }, false) {
  server_.start();
}

void InsertAction::release(const Active& a) { node_.guard().release(a.needle, kHolder); }

void InsertAction::shutdown() {
  std::lock_guard<PiMutex> lk(mutex_);
  if (active_) {
    release(*active_);
    needle_sim::InsertNeedleResult r;
    r.message = "the node shuts down";
    active_->gh.setAborted(r, r.message);
    active_.reset();
  }
}

needle_sim::InsertNeedleResult InsertAction::result(const Active& a, const Observables& o, const std::string& msg) const {
  needle_sim::InsertNeedleResult r;
  const NeedleObservation& n = o.needles[a.needle];
  const Vec3 target = a.target >= 0 ? o.targets[a.target].position : a.point;
  r.final_distance = (n.tip - target).norm();
  r.error_bound = a.target >= 0 && a.target < static_cast<int>(o.targets.size()) && o.targets[a.target].has_error
                      ? o.targets[a.target].error_bound
                                                                 : std::numeric_limits<double>::quiet_NaN();
  r.inserted = (n.base - a.base0).dot(a.axis);
  r.state = toString(n.state);
  r.max_tip_speed = a.max_tip_speed;
  r.message = msg;
  return r;
}

void InsertAction::onGoal(Server::GoalHandle gh) {
  const needle_sim::InsertNeedleGoal& g = *gh.getGoal();
  needle_sim::InsertNeedleResult rejected;
  auto reject = [&](const std::string& why) {
    rejected.message = why;
    rejected.final_distance = rejected.error_bound = rejected.inserted = rejected.max_tip_speed =
        std::numeric_limits<double>::quiet_NaN();
    ROS_WARN("needle_sim: ~insert goal rejected: %s", why.c_str());
    gh.setRejected(rejected, why);
  };
  const int needle = node_.needleIndex(g.needle);
  if (needle < 0) return reject("needle: no needle named '" + g.needle + "'");
  const double speed = g.speed == 0 ? default_speed_ : g.speed;
  const double max_speed = node_.guard().limits().max_speed;
  if (!(speed > 0) || !(speed <= max_speed))
    return reject("speed: " + std::to_string(speed) + " m/s is outside (0, ~max_speed = " + std::to_string(max_speed) + "]");
  if (!std::isfinite(g.depth) || g.depth < 0) return reject("depth: must be finite and >= 0");
  if (!std::isfinite(g.stop_distance) || g.stop_distance < 0) return reject("stop_distance: must be finite and >= 0");
  Active a;
  a.gh = gh;
  a.needle = needle;
  SimulatorRos::Plan plan;
  {
    std::lock_guard<PiMutex> sim_lock(node_.sim_mutex_);
    const Simulation& sim = *node_.sim_;
    if (!node_.failure_.empty()) return reject("the simulation has failed; call ~reset first");
    if (!g.target.empty()) {
      a.target = sim.findTarget(g.target);
      if (a.target < 0) return reject("target: no target named '" + g.target + "'");
    } else {
      a.point = fromPoint(g.point);
      if (!a.point.allFinite()) return reject("point: must be finite");
    }
    const double now = sim.time();
    const BaseTrajectory& traj = sim.needle(needle).trajectory();
    const BasePose from = traj.pose(now);
    a.axis = from.direction;
    a.base0 = from.position;
    const Vec3 target = a.target >= 0 ? sim.targetPosition(a.target) : a.point;
    const Vec3 tip = sim.needle(needle).tipPosition();
    // Along the axis: to stop_distance before the target, no further than depth.
    double length = (target - tip).dot(a.axis) - g.stop_distance;
    if (g.depth > 0) length = std::min(length, g.depth);
    if (!(length > 1e-9))
      return reject("nothing to do: the target is not ahead of the tip by more than stop_distance along the axis");
    PlanWaypoint w;
    w.time = length / speed;
    w.position = from.position + length * a.axis;
    w.orientation = orientationOf(from, traj.rest());
    plan.needle = needle;
    plan.waypoints = {w};
    plan.source = "~insert goal";
    // Checked now (rejected at once) and again by the stepping thread when it takes it.
    PlanPoses poses;
    const std::string why = node_.pipeline_->checkPlan(sim, needle, plan.waypoints, poses);
    if (!why.empty()) return reject("the motion breaks a limit: " + why);
    a.duration = w.time;
    std::lock_guard<PiMutex> lk(mutex_);
    // One source at a time: the goal holds the needle until it ends (a goal under way on
    // this needle is the same holder; its preemption below keeps the hold).
    std::string owner_why;
    if (!node_.guard().hold(needle, kHolder, now, owner_why)) {
      node_.warnRule(GuardRule::Owner, "~insert goal", owner_why);
      return reject("owner: " + owner_why);
    }
    plan.owner = kHolder;
    if (active_) {  // a new goal preempts the one under way (its plan is replaced)
      needle_sim::InsertNeedleResult r = result(*active_, node_.obs_, "preempted by a new goal");
      if (active_->needle != needle) release(*active_);
      auto old = active_->gh;
      node_.out_->post([old, r]() mutable { old.setCanceled(r, r.message); });
    }
    gh.setAccepted();
    active_ = a;
  }
  const std::string id = gh.getGoalID().id;
  plan.done = [this, id](const std::string& why) {  // stepping thread
    std::lock_guard<PiMutex> lk(mutex_);
    if (!active_ || active_->gh.getGoalID().id != id) return;
    if (why.empty()) {
      active_->taken = true;
      active_->end = node_.sim_->time() + active_->duration;  // the plan starts now
      return;
    }
    needle_sim::InsertNeedleResult r = result(*active_, node_.obs_, "the motion breaks a limit: " + why);
    release(*active_);
    auto h = active_->gh;
    active_.reset();
    node_.out_->post([h, r]() mutable { h.setAborted(r, r.message); });
  };
  node_.queuePlan(std::move(plan));
}

void InsertAction::onCancel(Server::GoalHandle gh) {
  std::lock_guard<PiMutex> sim_lock(node_.sim_mutex_);  // (the order of onGoal: actionlib, sim, this)
  std::lock_guard<PiMutex> lk(mutex_);
  if (!active_ || active_->gh.getGoalID().id != gh.getGoalID().id) return;
  node_.holdNeedle(active_->needle);  // the needle holds where it is
  const needle_sim::InsertNeedleResult r = result(*active_, node_.obs_, "preempted: the needle holds");
  release(*active_);
  active_->gh.setCanceled(r, r.message);
  active_.reset();
}

void InsertAction::superseded(int needle, const std::string& by) {
  std::lock_guard<PiMutex> lk(mutex_);
  if (!active_ || active_->needle != needle) return;
  const needle_sim::InsertNeedleResult r = result(*active_, node_.obs_, "aborted: " + by + " took over the needle");
  release(*active_);
  auto h = active_->gh;
  active_.reset();
  node_.out_->post([h, r]() mutable { h.setAborted(r, r.message); });
}

void InsertAction::update(const Observables& o) {
  std::lock_guard<PiMutex> lk(mutex_);
  if (!active_ || !active_->taken) return;
  Active& a = *active_;
  if (a.needle < node_.tip_speed_.numNeedles())
    a.max_tip_speed = std::max(a.max_tip_speed, node_.tip_speed_.speed(a.needle));
  if (a.target >= static_cast<int>(o.targets.size())) return;  // (a reset removed it: failed() ends the goal)
  const NeedleObservation& n = o.needles[a.needle];
  const Vec3 target = a.target >= 0 ? o.targets[a.target].position : a.point;
  // Done when the motion is (its plan may have been slowed down by new limits since).
  const double end = std::max(a.end, node_.sim_->needle(a.needle).trajectory().lastTime());
  if (o.time >= end - 1e-9) {
    needle_sim::InsertNeedleResult r = result(a, o, "inserted");
    release(a);
    auto h = a.gh;
    active_.reset();
    node_.out_->post([h, r]() mutable { h.setSucceeded(r, r.message); });
    return;
  }
  if (a.last_feedback >= 0 && o.time - a.last_feedback < 0.1 - 1e-9) return;
  a.last_feedback = o.time;
  needle_sim::InsertNeedleFeedback fb;
  fb.distance = (n.tip - target).norm();
  fb.inserted = (n.base - a.base0).dot(a.axis);
  fb.force = toVector(n.holder_force_base);
  fb.axial_force = n.axial_force;  // observables.hpp: negative when the tissue resists the insertion
  fb.state = toString(n.state);
  fb.max_tip_speed = a.max_tip_speed;
  auto h = a.gh;
  node_.out_->post([h, fb]() mutable { h.publishFeedback(fb); });
}

void InsertAction::abort(const std::string& why) {
  std::lock_guard<PiMutex> lk(mutex_);
  if (!active_) return;
  needle_sim::InsertNeedleResult r;
  r.message = why;
  r.final_distance = r.error_bound = r.inserted = std::numeric_limits<double>::quiet_NaN();
  r.max_tip_speed = active_->max_tip_speed;
  release(*active_);
  auto h = active_->gh;
  active_.reset();
  node_.out_->post([h, r]() mutable { h.setAborted(r, r.message); });
}

}  // namespace needle_sim

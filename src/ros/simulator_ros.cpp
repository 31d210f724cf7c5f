#include "needle_sim/ros/simulator_ros.hpp"
#include "needle_sim/sim/prediction.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>

#include <geometry_msgs/PointStamped.h>
#include <geometry_msgs/TransformStamped.h>
#include <geometry_msgs/WrenchStamped.h>
#include <nav_msgs/Path.h>
#include <sensor_msgs/PointCloud2.h>
#include <sensor_msgs/point_cloud2_iterator.h>
#include <visualization_msgs/MarkerArray.h>

#include "needle_sim/core/blas_threads.hpp"
#include "needle_sim/core/error.hpp"
#include <needle_sim/SimStatus.h>
#include <needle_sim/TargetState.h>
#include "needle_sim/scene/scene_loader.hpp"

namespace needle_sim {

CommandCheck checkCommand(const Vec3& position, const Eigen::Quaterniond& orientation, const BasePose& last,
                          const BasePose& rest, double dt, double max_speed, const Vec3& lo, const Vec3& hi,
                          double margin) {
  CommandCheck c;
  if (!position.allFinite() || !orientation.coeffs().allFinite()) {
    c.verdict = CommandCheck::Verdict::Reject;
    c.reason = "non-finite position or orientation";
    return c;
  }
  if (orientation.norm() < 1e-6) {
    c.verdict = CommandCheck::Verdict::Reject;
    c.reason = "zero quaternion";
    return c;
  }
  if (((position - (lo - Vec3::Constant(margin))).array() < 0).any() ||
      ((position - (hi + Vec3::Constant(margin))).array() > 0).any()) {
    c.verdict = CommandCheck::Verdict::Reject;
    c.reason = "position outside the workspace (the tissue's box plus ~workspace_margin)";
    return c;
  }
  const Eigen::Quaterniond q = orientation.normalized();
  const Vec3 d = q * Vec3::UnitX();
  // Roll: the twist about the axis of q relative to the frame that carries x to the rest
  // axis and then, by the smallest rotation, to d (BaseTrajectory's convention). The rest
  // pose's own frame is that one rolled by rest.roll, so the twist is the roll itself.
  const Eigen::Quaterniond ref =
      Eigen::Quaterniond::FromTwoVectors(rest.direction, d) * Eigen::Quaterniond::FromTwoVectors(Vec3::UnitX(), rest.direction);
  const Eigen::Quaterniond twist = ref.conjugate() * q;
  c.pose.position = position;
  c.pose.direction = d.normalized();
  c.pose.roll = 2 * std::atan2(twist.x(), twist.w());
  const double step = (position - last.position).norm(), limit = max_speed * dt;
  if (step > limit) {
    c.verdict = CommandCheck::Verdict::Clamp;
    c.reason = "faster than ~max_speed";
    c.pose.position = last.position + (position - last.position) * (limit / step);
  }
  return c;
}

Eigen::Quaterniond nodeFrame(const NeedleBody& needle, int node) {
  // The beam's node rotation carries the node's rest frame to its current one; the rest
  // frame in the command convention is the rest base orientation.
  const BasePose& rest = needle.trajectory().rest();
  const Eigen::Quaterniond rest_frame = Eigen::Quaterniond::FromTwoVectors(Vec3::UnitX(), rest.direction) *
                                        Eigen::AngleAxisd(rest.roll, Vec3::UnitX());
  return (needle.state().q[node] * rest_frame).normalized();
}

SimulatorRos::SimulatorRos(ros::NodeHandle nh, ros::NodeHandle pnh) : nh_(nh), pnh_(pnh) {
  if (!pnh_.getParam("scene", scene_file_))
    throw InputError("", "~scene", "missing private parameter: the scene YAML file");
  pnh_.param("set", overrides_, std::vector<std::string>{});
  pnh_.param<std::string>("tissue_frame", frame_, "tissue");
  pnh_.param<std::string>("command_source", command_source_, "topic");
  pnh_.param("max_speed", max_speed_, 0.05);
  pnh_.param("command_timeout", command_timeout_, 0.5);
  pnh_.param("command_latency", command_latency_, 0.005);
  if (!(command_latency_ >= 0)) throw InputError("", "~command_latency", "must be >= 0");
  pnh_.param("workspace_margin", workspace_margin_, 0.2);
  pnh_.param("as_fast_as_possible", as_fast_, false);
  pnh_.param("display_rate", display_rate_, 30.0);
  pnh_.param("output_period", output_period_, 0.001);
  if (!(output_period_ >= 0) || !(output_period_ <= 1.0)) throw InputError("", "~output_period", "must be in [0, 1] s");
  pnh_.param("predict_dt", predict_dt_, 0.01);
  pnh_.param("predict_sample_period", predict_sample_period_, 0.05);
  pnh_.param("predict_max_steps", predict_max_steps_, 100000);
  if (!(predict_dt_ > 0) || !std::isfinite(predict_dt_)) throw InputError("", "~predict_dt", "must be > 0");
  if (!(predict_sample_period_ > 0) || !std::isfinite(predict_sample_period_))
    throw InputError("", "~predict_sample_period", "must be > 0");
  if (predict_max_steps_ < 1) throw InputError("", "~predict_max_steps", "must be >= 1");
  int blas_threads = 1;
  pnh_.param("blas_threads", blas_threads, 1);
  if (blas_threads < 1) throw InputError("", "~blas_threads", "must be >= 1");
  setBlasThreads(blas_threads);  // OpenBLAS threads spin between the small per-step solves
  if (!(display_rate_ > 0)) throw InputError("", "~display_rate", "must be > 0");
  if (command_source_ != "topic" && command_source_ != "scene" && command_source_ != "tf")
    throw InputError("", "~command_source", "must be topic, scene or tf, got '" + command_source_ + "'");
  if (!(max_speed_ > 0)) throw InputError("", "~max_speed", "must be > 0");
  scene_ = loadScene(scene_file_, overrides_);
  if (command_source_ != "scene")
    for (auto& n : scene_.needles) n.motion.clear();  // the base follows the commands only
  if (command_source_ == "tf") {
    std::string single;
    pnh_.param<std::string>("needle_base_frame", single, "");
    for (const auto& n : scene_.needles)
      base_frames_.push_back(!single.empty() && scene_.needles.size() == 1 ? single : n.name + "_base");
    tf_buffer_ = std::make_unique<tf2_ros::Buffer>();
    tf_listener_ = std::make_unique<tf2_ros::TransformListener>(*tf_buffer_, nh_);
  }
  load();

  status_pub_ = nh_.advertise<needle_sim::SimStatus>("status", 10);
  cloud_pub_ = nh_.advertise<sensor_msgs::PointCloud2>("tissue/deformation", 2);
  surface_pub_ = nh_.advertise<visualization_msgs::Marker>("tissue/surface", 2);
  error_pub_ = nh_.advertise<visualization_msgs::MarkerArray>("tissue/error_markers", 2);
  target_pub_ = nh_.advertise<geometry_msgs::PointStamped>("target", 10);
  target_state_pub_ = nh_.advertise<needle_sim::TargetState>("target/state", 50);
  tf_broadcaster_ = std::make_unique<tf2_ros::TransformBroadcaster>();
  updater_ = std::make_unique<diagnostic_updater::Updater>(nh_, pnh_);
  updater_->setHardwareID("needle_sim/" + scene_.name);
  updater_->add("simulation", this, &SimulatorRos::diagnose);
  diag_timer_ = nh_.createTimer(ros::Duration(1.0), [this](const ros::TimerEvent&) { updater_->update(); });
  for (int i = 0; i < static_cast<int>(scene_.needles.size()); ++i) {
    const std::string& name = scene_.needles[i].name;
    wrench_pubs_.push_back(nh_.advertise<geometry_msgs::WrenchStamped>(name + "/wrench", 10));
    path_pubs_.push_back(nh_.advertise<nav_msgs::Path>(name + "/path", 10));
    if (command_source_ == "topic") {
      command_subs_.push_back(nh_.subscribe<geometry_msgs::PoseStamped>(
          name + "/command_pose", 100, [this, i](const geometry_msgs::PoseStamped::ConstPtr& m) { onCommand(i, m); }));
      command_subs_.push_back(nh_.subscribe<needle_sim::NeedleTrajectory>(
          name + "/command_trajectory", 10,
          [this, i](const needle_sim::NeedleTrajectory::ConstPtr& m) { onTrajectory(i, m); }));
    }
  }
  reset_srv_ = nh_.advertiseService("reset", &SimulatorRos::onReset, this);
  set_target_srv_ = nh_.advertiseService("set_target", &SimulatorRos::onSetTarget, this);
  {
    ros::AdvertiseServiceOptions o = ros::AdvertiseServiceOptions::create<needle_sim::PredictInsertion>(
        "predict",
        [this](needle_sim::PredictInsertion::Request& q, needle_sim::PredictInsertion::Response& r) {
          return onPredict(q, r);
        },
        ros::VoidConstPtr(), &predict_queue_);
    predict_srv_ = nh_.advertiseService(o);
    predict_spinner_ = std::make_unique<ros::AsyncSpinner>(1, &predict_queue_);
    predict_spinner_->start();
  }
  out_thread_ = std::thread(&SimulatorRos::outputLoop, this);
  thread_ = std::thread(&SimulatorRos::worker, this);
  if (!as_fast_) timer_ = nh_.createTimer(ros::Duration(scene_.dt), &SimulatorRos::onTimer, this);
  ROS_INFO("needle_sim: scene '%s' (%s), %d DOFs, dt %g s, commands from %s", scene_.name.c_str(), scene_file_.c_str(),
           sim_->numDofs(), scene_.dt, command_source_.c_str());
}

SimulatorRos::~SimulatorRos() {
  // No callback may start while the threads it would touch are joined and members go.
  reset_srv_.shutdown();
  set_target_srv_.shutdown();
  for (auto& sub : command_subs_) sub.shutdown();
  diag_timer_.stop();
  predict_srv_.shutdown();
  if (predict_spinner_) predict_spinner_->stop();  // waits for a prediction under way
  timer_.stop();
  {
    std::lock_guard<std::mutex> lk(queue_mutex_);
    stop_ = true;
  }
  wake_.notify_all();
  if (thread_.joinable()) thread_.join();
  {
    std::lock_guard<std::mutex> lk(out_mutex_);
    out_stop_ = true;
  }
  out_cv_.notify_all();
  if (out_thread_.joinable()) out_thread_.join();
}

void SimulatorRos::postJob(std::function<void()> job) {
  bool wake;
  {
    std::lock_guard<std::mutex> lk(out_mutex_);
    wake = out_queue_.empty() && (output_period_ == 0 || out_idle_);
    if (out_queue_.size() >= kOutQueue) {  // the sender fell far behind: the oldest goes
      out_queue_.pop_front();
      ++out_dropped_;
    }
    out_queue_.push_back(std::move(job));
  }
  // The output thread takes the whole queue at once. With an output period it wakes on its
  // own: waking it from here cost the stepping thread 5-10 % of a 0.2 ms step (futex wake,
  // and the woken thread often preempting this one on a 2-core machine). Only when it has
  // gone idle (nothing to send for a while) does a job wake it.
  if (wake) out_cv_.notify_one();
}

void SimulatorRos::outputLoop() {
  // Periodic wake-ups while jobs come; idle (woken by the next job) after ~50 empty periods,
  // so that a failed or paused simulation costs nothing.
  int empty = 0;
  for (;;) {
    std::deque<std::function<void()>> jobs;
    {
      std::unique_lock<std::mutex> lk(out_mutex_);
      auto ready = [&] { return out_stop_ || !out_queue_.empty(); };
      if (output_period_ > 0 && empty < 50) {
        out_cv_.wait_for(lk, std::chrono::duration<double>(output_period_), ready);
        if (!ready()) {
          ++empty;
          continue;
        }
      } else {
        out_idle_ = true;
        out_cv_.wait(lk, ready);
        out_idle_ = false;
      }
      empty = 0;
      if (out_queue_.empty() && out_stop_) return;
      jobs.swap(out_queue_);
    }
    const auto t0 = ros::WallTime::now();
    for (auto& j : jobs) j();
    out_ms_total_ = out_ms_total_ + (ros::WallTime::now() - t0).toSec() * 1e3;
  }
}

void SimulatorRos::load() {
  sim_ = std::make_unique<Simulation>(scene_);
  makeLabels();
  {
    std::lock_guard<std::mutex> lk(queue_mutex_);
    last_pose_.clear();
    for (const auto& n : scene_.needles) last_pose_.push_back({n.base_position, n.base_direction, n.base_roll});
    last_stamp_.assign(scene_.needles.size(), ros::Time(0));
    commands_.clear();
    plans_.clear();
    pending_ = 0;
    scheduled_ = 0;
    start_time_ = ros::Time::now();
  }
  failure_.clear();
  step_ms_max_ = 0;
  rtf_window_.clear();
  if (sim_->hasTissue()) {
    lo_ = sim_->tissue().mesh().boundsMin();
    hi_ = sim_->tissue().mesh().boundsMax();
  } else {
    lo_ = hi_ = scene_.needles.empty() ? Vec3::Zero() : scene_.needles[0].base_position;
  }
}

// The simulation follows ROS time (the wall clock, or /clock under /use_sim_time): at
// each tick it is due floor(elapsed / dt) steps since the start, whatever the tick rate, so
// a bag replayed with --clock gives the same steps as the recording. A clock that jumps
// back (a bag played in a loop) restarts the scene.
void SimulatorRos::onTimer(const ros::TimerEvent&) {
  const ros::Time now = ros::Time::now();
  if (now.isZero()) return;  // sim time before the first /clock
  if (tf_buffer_) lookupTfCommands();
  bool restart = false;
  {
    std::lock_guard<std::mutex> lk(queue_mutex_);
    if (start_time_.isZero() || now < last_tick_) {
      restart = !start_time_.isZero();
      start_time_ = now;
      scheduled_ = 0;
    }
    last_tick_ = now;
    const long due = static_cast<long>(std::floor((now - start_time_).toSec() / scene_.dt + 1e-6));
    if (due > scheduled_) {
      if (pending_ > 0) ++overruns_;  // the previous period's step has not started yet
      pending_ = static_cast<int>(std::min<long>(pending_ + (due - scheduled_), 100000));
      scheduled_ = due;
    }
  }
  if (restart) {
    ROS_WARN("needle_sim: time jumped back (bag loop?): the scene restarts");
    std_srvs::Trigger::Request req;
    std_srvs::Trigger::Response res;
    onReset(req, res);
    return;
  }
  wake_.notify_one();
}

void SimulatorRos::onCommand(int needle, const geometry_msgs::PoseStamped::ConstPtr& m) {
  const Vec3 p(m->pose.position.x, m->pose.position.y, m->pose.position.z);
  const Eigen::Quaterniond q(m->pose.orientation.w, m->pose.orientation.x, m->pose.orientation.y, m->pose.orientation.z);
  acceptCommand(needle, p, q, m->header.stamp, scene_.needles[needle].name + "/command_pose");
}

void SimulatorRos::lookupTfCommands() {
  for (int i = 0; i < static_cast<int>(base_frames_.size()); ++i) {
    geometry_msgs::TransformStamped tr;
    try {
      tr = tf_buffer_->lookupTransform(frame_, base_frames_[i], ros::Time(0));
    } catch (const tf2::TransformException& e) {
      ++tf_failures_;
      ROS_WARN_THROTTLE(1.0, "needle_sim: no base pose from tf (%s -> %s): %s; the base holds", frame_.c_str(),
                        base_frames_[i].c_str(), e.what());
      continue;
    }
    {
      std::lock_guard<std::mutex> lk(queue_mutex_);
      if (!tr.header.stamp.isZero() && tr.header.stamp == last_stamp_[i]) continue;  // nothing new
    }
    const auto& t = tr.transform;
    acceptCommand(i, Vec3(t.translation.x, t.translation.y, t.translation.z),
                  Eigen::Quaterniond(t.rotation.w, t.rotation.x, t.rotation.y, t.rotation.z), tr.header.stamp,
                  "tf " + base_frames_[i]);
  }
}

void SimulatorRos::acceptCommand(int needle, const Vec3& p, const Eigen::Quaterniond& q, const ros::Time& stamp,
                                 const std::string& source) {
  const char* name = source.c_str();
  if (!stamp.isZero() && (ros::Time::now() - stamp).toSec() > command_timeout_) {
    ++rejected_;
    ROS_WARN_THROTTLE(1.0, "needle_sim: %s rejected: stale (older than ~command_timeout = %g s)", name,
                      command_timeout_);
    return;
  }
  std::lock_guard<std::mutex> lk(queue_mutex_);
  const auto& nsc = scene_.needles[needle];
  double interval = scene_.dt;
  if (!stamp.isZero() && !last_stamp_[needle].isZero())
    interval = std::clamp((stamp - last_stamp_[needle]).toSec(), scene_.dt, 1.0);
  const CommandCheck c = checkCommand(p, q, last_pose_[needle], {nsc.base_position, nsc.base_direction, nsc.base_roll}, interval,
                                      max_speed_, lo_, hi_, workspace_margin_);
  if (c.verdict == CommandCheck::Verdict::Reject) {
    ++rejected_;
    ROS_WARN_THROTTLE(1.0, "needle_sim: %s rejected: %s", name, c.reason.c_str());
    return;
  }
  if (c.verdict == CommandCheck::Verdict::Clamp) {
    ++clamped_;
    ROS_WARN_THROTTLE(1.0, "needle_sim: %s clamped: %s (%g m/s)", name, c.reason.c_str(), max_speed_);
  }
  last_pose_[needle] = c.pose;
  last_stamp_[needle] = stamp;
  const double at = (!stamp.isZero() && !start_time_.isZero())
                       ? (stamp - start_time_).toSec() + command_latency_
                       : std::numeric_limits<double>::quiet_NaN();
  commands_.push_back({needle, c.pose, interval, at});
}

std::string SimulatorRos::checkPlan(int needle, const needle_sim::NeedleTrajectory& m, const BasePose& from,
                                   Plan& plan) const {
  const auto& nsc = scene_.needles[needle];
  const BasePose rest{nsc.base_position, nsc.base_direction, nsc.base_roll};
  if (m.waypoints.empty()) return "no waypoints";
  plan = Plan{needle, {}};
  BasePose prev = from;
  double t_prev = 0;
  for (size_t k = 0; k < m.waypoints.size(); ++k) {
    const auto& w = m.waypoints[k];
    const double t = w.time_from_start.toSec();
    if (!std::isfinite(t) || t < 0 || (k > 0 && t <= t_prev))
      return "waypoint " + std::to_string(k) + ": time_from_start not increasing";
    const Vec3 p(w.pose.position.x, w.pose.position.y, w.pose.position.z);
    const Eigen::Quaterniond q(w.pose.orientation.w, w.pose.orientation.x, w.pose.orientation.y, w.pose.orientation.z);
    // A plan is not silently changed: a waypoint too fast for ~max_speed rejects it.
    const CommandCheck c =
        checkCommand(p, q, prev, rest, std::max(t - t_prev, scene_.dt), max_speed_, lo_, hi_, workspace_margin_);
    if (c.verdict != CommandCheck::Verdict::Accept) return "waypoint " + std::to_string(k) + ": " + c.reason;
    plan.waypoints.emplace_back(t, c.pose);
    prev = c.pose;
    t_prev = t;
  }
  return "";
}

void SimulatorRos::onTrajectory(int needle, const needle_sim::NeedleTrajectory::ConstPtr& m) {
  std::lock_guard<std::mutex> lk(queue_mutex_);
  Plan plan;
  const std::string why = checkPlan(needle, *m, last_pose_[needle], plan);
  if (!why.empty()) {
    ++rejected_;
    ROS_WARN_THROTTLE(1.0, "needle_sim: %s/command_trajectory rejected: %s", scene_.needles[needle].name.c_str(),
                      why.c_str());
    return;
  }
  last_pose_[needle] = plan.waypoints.back().second;
  last_stamp_[needle] = ros::Time(0);
  plans_.push_back(std::move(plan));
}

bool SimulatorRos::onPredict(needle_sim::PredictInsertion::Request& req, needle_sim::PredictInsertion::Response& res) {
  const auto w0 = ros::WallTime::now();
  res.success = false;
  res.final_target_tip_distance = std::numeric_limits<double>::quiet_NaN();
  auto refuse = [&](const std::string& why) {
    res.message = why;
    ROS_WARN("needle_sim: predict refused: %s", why.c_str());
    return true;
  };
  int needle = req.needle.empty() ? 0 : -1;
  for (int i = 0; i < static_cast<int>(scene_.needles.size()) && needle < 0; ++i)
    if (scene_.needles[i].name == req.needle) needle = i;
  if (needle < 0 || needle >= static_cast<int>(scene_.needles.size()))
    return refuse("needle: no needle named '" + req.needle + "'");
  InsertionPlan plan;
  plan.needle = needle;
  plan.duration = req.duration;
  plan.dt = req.dt > 0 ? req.dt : predict_dt_;
  plan.sample_period = req.sample_period > 0 ? req.sample_period : predict_sample_period_;
  if (!std::isfinite(req.dt) || req.dt < 0) return refuse("dt: must be finite and >= 0");
  if (!std::isfinite(req.sample_period) || req.sample_period < 0) return refuse("sample_period: must be finite and >= 0");
  std::unique_ptr<Simulation> snapshot;
  int target = -1;
  {
    // The state of now, copied under the lock (about a millisecond); the prediction runs
    // without it, so the live simulation goes on meanwhile.
    std::lock_guard<std::mutex> lk(sim_mutex_);
    if (!failure_.empty()) return refuse("the simulation has failed (" + failure_ + "); reset first");
    target = req.target.empty() ? (sim_->numTargets() > 0 ? std::min(primary_target_, sim_->numTargets() - 1) : -1)
                                : sim_->findTarget(req.target);
    if (!req.target.empty() && target < 0) return refuse("target: no target named '" + req.target + "'");
    Plan checked;
    const BasePose from = sim_->needle(needle).trajectory().pose(sim_->time());
    const std::string why = checkPlan(needle, req.trajectory, from, checked);
    if (!why.empty()) return refuse("trajectory: " + why);
    plan.waypoints = checked.waypoints;
    snapshot = std::make_unique<Simulation>(*sim_);
  }
  Prediction p;
  try {
    p = predictInsertion(*snapshot, plan, predict_max_steps_);
  } catch (const InputError& e) {
    return refuse(e.what());
  } catch (const NumericalError& e) {
    res.message = std::string("the predicted run failed: ") + e.what();
    ROS_WARN("needle_sim: predict: %s", res.message.c_str());
    return true;
  }
  for (const auto& s : p.samples) {
    res.time.push_back(s.t);
    geometry_msgs::Point tip;
    tip.x = s.tips[needle].x();
    tip.y = s.tips[needle].y();
    tip.z = s.tips[needle].z();
    res.tip_position.push_back(tip);
    geometry_msgs::Vector3 f;
    f.x = s.base_forces[needle].x();
    f.y = s.base_forces[needle].y();
    f.z = s.base_forces[needle].z();
    res.base_force.push_back(f);
    if (target >= 0) {
      geometry_msgs::Point q;
      q.x = s.targets[target].x();
      q.y = s.targets[target].y();
      q.z = s.targets[target].z();
      res.target_position.push_back(q);
      res.target_tip_distance.push_back(s.tip_distances[target]);
    }
  }
  if (target >= 0) res.final_target_tip_distance = res.target_tip_distance.back();
  res.steps = p.steps;
  res.max_dofs = p.max_dofs;
  res.compute_time = (ros::WallTime::now() - w0).toSec();
  res.success = true;
  char buf[160];
  std::snprintf(buf, sizeof buf, "predicted %.3g s in %d steps of %.3g s (%.3f s wall)", p.samples.back().t, p.steps,
                plan.dt, res.compute_time);
  res.message = buf;
  return true;
}

bool SimulatorRos::onReset(std_srvs::Trigger::Request&, std_srvs::Trigger::Response& res) {
  std::lock_guard<std::mutex> lk(sim_mutex_);
  try {
    load();
  } catch (const std::exception& e) {
    res.success = false;
    res.message = e.what();
    return true;
  }
  overruns_ = rejected_ = clamped_ = 0;
  primary_target_ = 0;
  res.success = true;
  res.message = "reset to the initial state of scene '" + scene_.name + "'";
  return true;
}

bool SimulatorRos::onSetTarget(needle_sim::SetTarget::Request& req, needle_sim::SetTarget::Response& res) {
  std::lock_guard<std::mutex> lk(sim_mutex_);
  const Vec3 p(req.point.x, req.point.y, req.point.z);
  try {
    primary_target_ = sim_->setTarget(req.name, p);
    makeLabels();
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

void SimulatorRos::worker() {
  for (;;) {
    std::vector<Command> cmds;
    std::vector<Plan> plans;
    {
      std::unique_lock<std::mutex> lk(queue_mutex_);
      wake_.wait(lk, [&] { return stop_ || pending_ > 0 || as_fast_; });
      if (stop_) return;
      if (pending_ > 0) --pending_;
      cmds.swap(commands_);
      plans.swap(plans_);
    }
    std::lock_guard<std::mutex> lk(sim_mutex_);
    // A command becomes a keyframe one command interval after the needle's previous one
    // (so that a stream of poses is followed smoothly), and never earlier than the end of
    // this step.
    const double now = sim_->time();
    auto anchor = [&](BaseTrajectory& traj) {  // the base moves on from where it is now
      if (traj.lastTime() < now) traj.add(now, traj.pose(now));
      if (traj.size() > 256) traj.dropBefore(now);
    };
    for (const auto& c : cmds) {
      auto& traj = sim_->needle(c.needle).trajectory();
      const double t = std::max(now + scene_.dt, std::isnan(c.at) ? traj.lastTime() + c.interval : c.at);
      anchor(traj);
      try {
        traj.add(t, c.pose);
      } catch (const std::invalid_argument&) {
        // a second command for the same step: the later one wins
        traj.replaceLast(c.pose);
      }
    }
    // A plan replaces what was commanded after now; its waypoints are timed from now.
    for (const auto& p : plans) {
      auto& traj = sim_->needle(p.needle).trajectory();
      anchor(traj);
      traj.replaceFrom(now, scene_.dt, p.waypoints);
    }
    stepOnce();
  }
}

void SimulatorRos::stepOnce() {
  StepStats s;
  double ms = 0;
  if (failure_.empty()) {
    const auto t0 = ros::WallTime::now();
    try {
      s = sim_->step();
    } catch (const NumericalError& e) {
      failure_ = e.what();
      ROS_ERROR("needle_sim: numerical failure, stepping stopped until reset: %s", e.what());
    }
    ms = (ros::WallTime::now() - t0).toSec() * 1e3;
    step_ms_max_ = std::max(step_ms_max_, ms);
  }
  const auto p0 = ros::WallTime::now();
  publish(s, ms);
  publish_ms_ = (ros::WallTime::now() - p0).toSec() * 1e3;
}

void SimulatorRos::makeLabels() {
  auto l = std::make_shared<Labels>();
  l->scene = scene_.name;
  for (int i = 0; i < sim_->numNeedles(); ++i) {
    l->needles.push_back(sim_->needle(i).name());
    if (l->needles.back() == "electrode") l->electrode = i;
  }
  for (int i = 0; i < sim_->numProbes(); ++i) {
    l->probes.push_back(sim_->probeName(i));
    l->probe_rest.push_back(scene_.probes[i].point);
  }
  for (int i = 0; i < sim_->numTargets(); ++i) {
    l->targets.push_back(sim_->targetName(i));
    l->target_rest.push_back(sim_->targetRest(i));
    l->target_start.push_back(sim_->targetStart(i));
  }
  labels_ = std::move(l);
}

void SimulatorRos::publish(const StepStats& s, double ms) {
  const ros::WallTime wall = ros::WallTime::now();
  rtf_window_.emplace_back(wall, sim_->time());
  while (rtf_window_.size() > 2 && (wall - rtf_window_.front().first).toSec() > 1.0) rtf_window_.pop_front();

  StepFrame f;
  f.stamp = ros::Time::now();
  f.labels = labels_;
  f.failure = failure_;
  f.step = sim_->stepIndex();
  f.sim_time = sim_->time();
  f.dofs = sim_->numDofs();
  f.elements = sim_->hasTissue() ? sim_->tissue().mesh().numElements() : 0;
  f.step_ms = ms;
  f.step_ms_max = step_ms_max_;
  f.publish_ms = publish_ms_;
  const double dw = (rtf_window_.back().first - rtf_window_.front().first).toSec();
  f.rtf = dw > 0 ? (rtf_window_.back().second - rtf_window_.front().second) / dw : 0.0;
  f.overruns = overruns_;
  f.rejected = rejected_;
  f.clamped = clamped_;
  f.linear_iterations = s.linear_iterations;
  f.constraint_points = s.constraint_points;
  if (const ErrorEstimate* e = sim_->lastEstimate()) f.eta_relative = e->energy > 0 ? e->global / e->energy : 0.0;
  const int nn = sim_->numNeedles(), nt = sim_->numTargets();
  f.interaction = sim_->interaction() != nullptr;
  if (f.interaction)
    for (int i = 0; i < nn; ++i) f.states.push_back(sim_->interaction()->state(i));
  if (failure_.empty()) {  // never publish a state that failed: the status alone
    for (int i = 0; i < sim_->numProbes(); ++i) f.probe_u.push_back(sim_->probeDisplacement(i));
    for (int i = 0; i < nn; ++i) {
      const NeedleBody& nd = sim_->needle(i);
      f.force.push_back(-nd.baseForce());  // on the holder
      f.moment.push_back(-nd.baseMoment());
      f.tip.push_back(nd.tipPosition());
    }
    f.primary = std::min(primary_target_, nt - 1);
    f.target_point = nt > 0 && target_pub_.getNumSubscribers() > 0;
    f.target_state = nt > 0 && target_state_pub_.getNumSubscribers() > 0;
    if (f.target_point || f.target_state)
      for (int i = 0; i < nt; ++i) {
        f.target_x.push_back(sim_->targetPosition(i));
        f.target_v.push_back(sim_->targetVelocity(i));
      }
  }
  postJob([this, f = std::move(f)] { sendStep(f); });
  if (!failure_.empty()) return;

  const ros::WallTime wnow = ros::WallTime::now();
  if ((wnow - last_display_).toSec() >= 1.0 / display_rate_) {
    last_display_ = wnow;
    publishDisplay();
  }
}

void SimulatorRos::sendStep(const StepFrame& f) {
  const Labels& l = *f.labels;
  auto point = [](const Vec3& v) {
    geometry_msgs::Point p;
    p.x = v.x(), p.y = v.y(), p.z = v.z();
    return p;
  };
  auto vector = [](const Vec3& v) {
    geometry_msgs::Vector3 p;
    p.x = v.x(), p.y = v.y(), p.z = v.z();
    return p;
  };
  needle_sim::SimStatus st;
  st.header.stamp = f.stamp;
  st.header.frame_id = frame_;
  st.scene = l.scene;
  st.state = f.failure.empty() ? "running" : "failed";
  st.message = f.failure;
  st.step = f.step;
  st.sim_time = f.sim_time;
  st.dofs = f.dofs;
  st.tissue_elements = f.elements;
  st.step_ms = f.step_ms;
  st.step_ms_max = f.step_ms_max;
  st.publish_ms = f.publish_ms;
  st.real_time_factor = f.rtf;
  st.overruns = f.overruns;
  st.rejected_commands = f.rejected;
  st.clamped_commands = f.clamped;
  st.linear_iterations = f.linear_iterations;
  st.constraint_points = f.constraint_points;
  st.needles = l.needles;
  for (size_t i = 0; i < l.needles.size(); ++i)
    st.insertion_states.push_back(f.interaction ? toString(f.states[i]) : "free");
  st.eta_relative = f.eta_relative;
  for (size_t i = 0; i < f.probe_u.size(); ++i) {
    needle_sim::Probe p;
    p.name = l.probes[i];
    p.rest = point(l.probe_rest[i]);
    p.displacement = vector(f.probe_u[i]);
    st.probes.push_back(p);
  }
  const std_msgs::Header header = st.header;
  status_pub_.publish(st);
  if (!f.failure.empty()) return;

  for (size_t i = 0; i < f.force.size(); ++i) {
    geometry_msgs::WrenchStamped w;
    w.header = header;
    w.wrench.force = vector(f.force[i]);
    w.wrench.torque = vector(f.moment[i]);
    wrench_pubs_[i].publish(w);
  }
  if (f.target_point) {
    geometry_msgs::PointStamped ps;
    ps.header = header;
    ps.point = point(f.target_x[f.primary]);
    target_pub_.publish(ps);
  }
  if (!f.target_state) return;
  const double nan = std::numeric_limits<double>::quiet_NaN();
  for (size_t i = 0; i < f.target_x.size(); ++i) {
    needle_sim::TargetState m;
    m.header = header;
    m.name = l.targets[i];
    const Vec3& x = f.target_x[i];
    m.planned = point(l.target_rest[i]);
    m.position = point(x);
    m.displacement = vector(x - l.target_start[i]);
    m.shift = vector(x - l.target_rest[i]);
    m.velocity = vector(f.target_v[i]);
    m.needles = l.needles;
    for (size_t n = 0; n < f.tip.size(); ++n) m.tip_distances.push_back((f.tip[n] - x).norm());
    m.needle_tip_distance = m.tip_distances.empty() ? nan : m.tip_distances[0];
    m.electrode_tip_distance = l.electrode >= 0 ? m.tip_distances[l.electrode] : nan;
    m.displacement_error_bound = nan;
    target_state_pub_.publish(m);
  }
}

void SimulatorRos::broadcastFrames(const std_msgs::Header& header) {
  std::vector<geometry_msgs::TransformStamped> tfs;
  for (int i = 0; i < sim_->numTargets(); ++i) {
    geometry_msgs::TransformStamped t;
    t.header = header;
    t.child_frame_id = "target/" + sim_->targetName(i);
    const Vec3 x = sim_->targetPosition(i);
    t.transform.translation.x = x.x(), t.transform.translation.y = x.y(), t.transform.translation.z = x.z();
    t.transform.rotation.w = 1;
    tfs.push_back(t);
    if (i == primary_target_) {
      t.child_frame_id = "target";
      tfs.push_back(t);
    }
  }
  // Needle tips, in the command poses' convention.
  for (int i = 0; i < sim_->numNeedles(); ++i) {
    const NeedleBody& nd = sim_->needle(i);
    geometry_msgs::TransformStamped t;
    t.header = header;
    t.child_frame_id = nd.name() + "_tip";
    const Vec3 x = nd.tipPosition();
    const Eigen::Quaterniond q = nodeFrame(nd, nd.beam().numNodes() - 1);
    t.transform.translation.x = x.x(), t.transform.translation.y = x.y(), t.transform.translation.z = x.z();
    t.transform.rotation.w = q.w(), t.transform.rotation.x = q.x(), t.transform.rotation.y = q.y(),
    t.transform.rotation.z = q.z();
    tfs.push_back(t);
  }
  if (!tfs.empty()) postJob([this, tfs = std::move(tfs)] { tf_broadcaster_->sendTransform(tfs); });
}

void SimulatorRos::publishDisplay() {
  std_msgs::Header header;
  header.stamp = ros::Time::now();
  header.frame_id = frame_;
  broadcastFrames(header);
  for (int i = 0; i < sim_->numNeedles(); ++i) {
    const NeedleBody& nd = sim_->needle(i);
    if (path_pubs_[i].getNumSubscribers() > 0) {
      nav_msgs::Path path;
      path.header = header;
      for (int k = 0; k < nd.beam().numNodes(); ++k) {
        geometry_msgs::PoseStamped ps;
        ps.header = header;
        const Vec3& p = nd.state().p[k];
        const Eigen::Quaterniond q = nodeFrame(nd, k);
        ps.pose.position.x = p.x(), ps.pose.position.y = p.y(), ps.pose.position.z = p.z();
        ps.pose.orientation.w = q.w(), ps.pose.orientation.x = q.x(), ps.pose.orientation.y = q.y(),
        ps.pose.orientation.z = q.z();
        path.poses.push_back(ps);
      }
      post(path_pubs_[i], std::move(path));
    }
  }
  if (!sim_->hasTissue()) return;
  // The tissue outputs are built on the output thread from a snapshot: positions, the
  // reference of the estimate, levels, the organ surface's vertices (a copy of the mesh only
  // when it changed). The SPR estimate runs there too, on its own model of the mesh.
  auto f = std::make_shared<DisplayFrame>();
  f->header = header;
  f->cloud = cloud_pub_.getNumSubscribers() > 0;
  f->surface = surface_pub_.getNumSubscribers() > 0;
  f->errors = error_pub_.getNumSubscribers() > 0;
  if (!f->cloud && !f->surface && !f->errors) return;
  const TissueBody& t = sim_->tissue();
  const HexMesh& mesh = t.mesh();
  if (!disp_mesh_ || disp_src_ != &mesh || disp_src_elements_ != mesh.numElements() || disp_src_nodes_ != mesh.numNodes()) {
    disp_mesh_ = std::make_shared<const HexMesh>(mesh);
    disp_src_ = &mesh;
    disp_src_elements_ = mesh.numElements();
    disp_src_nodes_ = mesh.numNodes();
  }
  f->mesh = disp_mesh_;
  f->x = t.positions();
  if (const VecX* r = sim_->estimateReference()) f->reference = *r;
  if (f->errors) f->level = sim_->elementLevels();
  if (f->surface)
    if (const EmbeddedSurface* organ = sim_->organSurface()) {
      f->organ_rest = organ->restPtr();
      organ->positions(f->x, f->organ_pos);
    }
  postJob([this, f] { buildDisplay(*f); });
}

void SimulatorRos::buildDisplay(const DisplayFrame& f) {
  const std_msgs::Header& header = f.header;
  const HexMesh& mesh = *f.mesh;
  if (out_mesh_ != f.mesh) {  // a new mesh: its model and estimator (once per mesh change)
    out_estimator_.reset();
    out_model_ = std::make_unique<CorotationalHexModel>(mesh, scene_.tissue.material);
    out_estimator_ = std::make_unique<SprEstimator>(*out_model_);
    faces_ = mesh.boundaryFaces();
    out_mesh_ = f.mesh;
  }
  const VecX& x = f.x;
  const VecX u = x - mesh.restPositions();
  ErrorEstimate est;
  if (f.cloud || f.errors) est = out_estimator_->estimate(x, f.reference.size() ? &f.reference : nullptr);
  if (f.cloud) {
    // Nodal values: displacement, and the average over the node's elements of the centroid
    // von Mises stress and of the SPR indicator eta.
    std::vector<float> vm(mesh.numNodes(), 0.f), eta(mesh.numNodes(), 0.f);
    std::vector<int> cnt(mesh.numNodes(), 0);
    for (int e = 0; e < mesh.numElements(); ++e) {
      const double v = SprEstimator::vonMises(est.centroid_stress[e]);
      for (int a : mesh.element(e)) {
        vm[a] += static_cast<float>(v);
        eta[a] += static_cast<float>(est.eta[e]);
        ++cnt[a];
      }
    }
    sensor_msgs::PointCloud2 cloud;
    cloud.header = header;
    sensor_msgs::PointCloud2Modifier mod(cloud);
    mod.setPointCloud2Fields(8, "x", 1, sensor_msgs::PointField::FLOAT32, "y", 1, sensor_msgs::PointField::FLOAT32,
                             "z", 1, sensor_msgs::PointField::FLOAT32, "dx", 1, sensor_msgs::PointField::FLOAT32,
                             "dy", 1, sensor_msgs::PointField::FLOAT32, "dz", 1, sensor_msgs::PointField::FLOAT32,
                             "von_mises", 1, sensor_msgs::PointField::FLOAT32, "eta", 1,
                             sensor_msgs::PointField::FLOAT32);
    mod.resize(mesh.numNodes());
    sensor_msgs::PointCloud2Iterator<float> it(cloud, "x");
    for (int n = 0; n < mesh.numNodes(); ++n, ++it) {
      for (int d = 0; d < 3; ++d) {
        it[d] = static_cast<float>(x[3 * n + d]);
        it[3 + d] = static_cast<float>(u[3 * n + d]);
      }
      it[6] = cnt[n] ? vm[n] / cnt[n] : 0.f;
      it[7] = cnt[n] ? eta[n] / cnt[n] : 0.f;
    }
    cloud_pub_.publish(cloud);
  }
  auto colour = [](double s) {  // 0 -> blue, 0.5 -> green, 1 -> red
    std_msgs::ColorRGBA c;
    s = std::clamp(s, 0.0, 1.0);
    c.r = static_cast<float>(std::clamp(2 * s - 1, 0.0, 1.0));
    c.g = static_cast<float>(1 - std::abs(2 * s - 1));
    c.b = static_cast<float>(std::clamp(1 - 2 * s, 0.0, 1.0));
    c.a = 1.f;
    return c;
  };
  if (f.surface) {
    // Triangle corners and their displacements: an immersed organ's own surface (carried by
    // the grid), else the mesh boundary (2 triangles per face).
    std::vector<Vec3> corner;
    std::vector<double> du;
    if (f.organ_rest) {
      const TriangleMesh& rest = *f.organ_rest;
      const std::vector<Vec3>& p = f.organ_pos;
      for (int tr = 0; tr < rest.numTriangles(); ++tr)
        for (int v : rest.triangle(tr)) {
          corner.push_back(p[v]);
          du.push_back((p[v] - rest.vertex(v)).norm());
        }
    } else {
      for (const auto& f : faces_)
        for (int k : {0, 1, 2, 0, 2, 3}) {
          const int n = f.nodes[k];
          corner.push_back(x.segment<3>(3 * n));
          du.push_back(u.segment<3>(3 * n).norm());
        }
    }
    const double umax = du.empty() ? 0.0 : *std::max_element(du.begin(), du.end());
    visualization_msgs::Marker m;
    m.header = header;
    m.ns = "tissue_surface";
    m.id = 0;
    m.type = visualization_msgs::Marker::TRIANGLE_LIST;
    m.action = visualization_msgs::Marker::ADD;
    m.pose.orientation.w = 1;
    m.scale.x = m.scale.y = m.scale.z = 1;
    m.color.a = 1;
    m.points.resize(corner.size());
    m.colors.resize(corner.size());
    for (size_t i = 0; i < corner.size(); ++i) {
      m.points[i].x = corner[i].x(), m.points[i].y = corner[i].y(), m.points[i].z = corner[i].z();
      m.colors[i] = colour(umax > 0 ? du[i] / umax : 0.0);
    }
    surface_pub_.publish(m);
  }
  if (f.errors) {
    const std::vector<int>& level = f.level;
    visualization_msgs::MarkerArray arr;
    visualization_msgs::Marker clear;
    clear.header = header;
    clear.action = visualization_msgs::Marker::DELETEALL;
    arr.markers.push_back(clear);
    const int levels = *std::max_element(level.begin(), level.end()) + 1;
    for (int L = 0; L < levels; ++L) {
      visualization_msgs::Marker m;
      m.header = header;
      m.ns = "level_" + std::to_string(L);
      m.id = L;
      m.type = visualization_msgs::Marker::CUBE_LIST;
      m.action = visualization_msgs::Marker::ADD;
      m.pose.orientation.w = 1;
      for (int e = 0; e < mesh.numElements(); ++e) {
        if (level[e] != L) continue;
        const auto X = mesh.elementCorners(e);
        if (m.points.empty()) {  // cube size: the element's rest extent (shrunk to see through)
          const Vec3 ext = X.colwise().maxCoeff() - X.colwise().minCoeff();
          m.scale.x = 0.6 * ext.x(), m.scale.y = 0.6 * ext.y(), m.scale.z = 0.6 * ext.z();
        }
        Vec3 c = Vec3::Zero();
        for (int a : mesh.element(e)) c += x.segment<3>(3 * a) / 8.0;
        geometry_msgs::Point p;
        p.x = c.x(), p.y = c.y(), p.z = c.z();
        m.points.push_back(p);
        std_msgs::ColorRGBA col = colour(est.max > 0 ? est.eta[e] / est.max : 0.0);
        col.a = 0.5f;
        m.colors.push_back(col);
      }
      if (!m.points.empty()) arr.markers.push_back(m);
    }
    error_pub_.publish(arr);
  }
}

void SimulatorRos::diagnose(diagnostic_updater::DiagnosticStatusWrapper& stat) {
  std::lock_guard<std::mutex> lk(sim_mutex_);
  const uint64_t rej = rejected_, cl = clamped_, ov = overruns_;
  if (!failure_.empty())
    stat.summary(diagnostic_msgs::DiagnosticStatus::ERROR, "numerical failure: " + failure_);
  else if (rej > diag_rejected_ || cl > diag_clamped_)
    stat.summary(diagnostic_msgs::DiagnosticStatus::WARN, "commands rejected or clamped in the last second");
  else if (ov > diag_overruns_)
    stat.summary(diagnostic_msgs::DiagnosticStatus::WARN, "steps overran their period in the last second");
  else
    stat.summary(diagnostic_msgs::DiagnosticStatus::OK, "running");
  diag_rejected_ = rej, diag_clamped_ = cl, diag_overruns_ = ov;
  stat.add("scene", scene_.name);
  stat.add("step", sim_->stepIndex());
  stat.add("sim_time", sim_->time());
  stat.add("dofs", sim_->numDofs());
  stat.add("step_ms_max", step_ms_max_);
  stat.add("overruns", ov);
  stat.add("rejected_commands", rej);
  stat.add("clamped_commands", cl);
  stat.add("tf_failures", static_cast<uint64_t>(tf_failures_));
  stat.add("output_thread_ms_total", out_ms_total_.load());
  stat.add("output_messages_dropped", out_dropped_.load());
}

}  // namespace needle_sim

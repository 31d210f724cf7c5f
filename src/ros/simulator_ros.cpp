// SimulatorRos: set-up, pacing by the ROS clock, the stepping thread. (Per-step messages and
// diagnostics: step_outputs.cpp; commands: command_input.cpp; services: services.cpp;
// display: display_outputs.cpp; the action: insert_action.cpp.)
#include "needle_sim/ros/simulator_ros.hpp"

#include <geometry_msgs/PointStamped.h>
#include <geometry_msgs/WrenchStamped.h>
#include <needle_sim/SimStatus.h>
#include <needle_sim/TargetState.h>

#include <pthread.h>
#include <sched.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <thread>

#include "conversions.hpp"
#include "display_outputs.hpp"
#include "insert_action.hpp"
#include "limits_reconfigure.hpp"
#include "node_assimilation.hpp"
#include "needle_sim/core/background_priority.hpp"
#include "needle_sim/core/blas_threads.hpp"
#include "needle_sim/core/denormals.hpp"
#include "needle_sim/core/error.hpp"
#include "needle_sim/scene/scene_check.hpp"
#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/sim/live_loop.hpp"
#include "node_parameters.hpp"
#include "output_queue.hpp"

namespace needle_sim {

SimulatorRos::SimulatorRos(ros::NodeHandle nh, ros::NodeHandle pnh) : nh_(nh), pnh_(pnh) {
  params_ = std::make_unique<NodeParameters>(readParameters(pnh_));
  const NodeParameters& P = *params_;
  setBlasThreads(P.blas_threads);  // OpenBLAS threads spin between the small per-step solves
  // Loading the scene comes before any step: its large factorisations may use more threads
  // (~setup_threads, 1 by default; 0: every core).
  Simulation::setSetupThreads(threadsOrEveryCore(P.setup_threads));
  scene_ = loadScene(P.scene_file, P.overrides);
  for (const std::string& w : sceneWarnings(scene_)) ROS_WARN_STREAM("needle_sim: " << w);
  // A real-time loop: a refreshed factor taken as soon as it is ready, lagged rotations for
  // nearly incompressible tissue (sim/live_loop.hpp; doc/ros_api.md, ~deterministic_factor and
  // ~rotation_drift).
  applyLiveLoop(scene_, {P.deterministic_factor, P.rotation_drift});
  if (scene_.solver.linear.rotation_drift > 0)
    ROS_INFO("needle_sim: lagged rotations, refreshed past %g rad (~rotation_drift; the CLI runs the scene with "
             "the rotations of every step)",
             scene_.solver.linear.rotation_drift);
  const std::vector<NeedleScene> scene_needles = scene_.needles;  // with their motion (pre-flight)
  if (P.command_source != "scene")
    for (auto& n : scene_.needles) n.motion.clear();  // the base follows the commands only
  tf_buffer_ = std::make_unique<tf2_ros::Buffer>();
  tf_listener_ = std::make_unique<tf2_ros::TransformListener>(*tf_buffer_, nh_);
  if (P.command_source == "tf")
    for (const auto& n : scene_.needles)
      base_frames_.push_back(!P.needle_base_frame.empty() && scene_.needles.size() == 1 ? P.needle_base_frame
                                                                                          : n.name + "_base");
  tf_last_stamp_.assign(scene_.needles.size(), ros::Time(0));
  tf_missing_.assign(scene_.needles.size(), 0);
  schedule_ = RealtimeSchedule(scene_.dt);
  // The coarsest step a prediction may take (doc/ros_api.md, ~predict_max_dt).
  predict_max_dt_ = P.predict_max_dt > 0 ? P.predict_max_dt : std::max(10 * scene_.dt, P.predict_dt);
  if (P.predict_dt > predict_max_dt_)
    throw InputError("", "~predict_dt", "must not exceed ~predict_max_dt = " + std::to_string(predict_max_dt_) + " s");
  tip_speed_peak_.assign(scene_.needles.size(), 0.0);
  tip_speed_over_.assign(scene_.needles.size(), 0);
  diag_tip_over_.assign(scene_.needles.size(), 0);
  load();
  if (P.preflight_wall > 0) {
    // Before any thread of the node runs: the copy's steps have the machine to themselves,
    // as the live loop will (minus what its outputs and clients cost).
    Scene own = scene_;
    own.needles = scene_needles;
    preflight_ = preflight(*sim_, own, {P.preflight_wall});
    preflight_run_ = true;
    if (preflight_.keepsRealTime())
      ROS_INFO("needle_sim: %s", preflight_.summary().c_str());
    else
      ROS_WARN("needle_sim: %s; started anyway (diagnostics keep the warning)", preflight_.summary().c_str());
  }
  // A later load (~reset) may come while prediction and error threads run BLAS: it keeps
  // the steps' thread count (changing it under running BLAS calls is not safe).
  Simulation::setSetupThreads(0);

  out_ = std::make_unique<OutputQueue>(P.output_period);
  display_ = std::make_unique<DisplayOutputs>(pnh_, P, scene_, *out_);
  // Per-step messages queue deeply: after a stall the steps catch up back to back, and a
  // status per step is what a client counts on.
  status_pub_ = pnh_.advertise<needle_sim::SimStatus>("status", 1000);
  target_pub_ = pnh_.advertise<geometry_msgs::PointStamped>("target", 10);
  target_state_pub_ = pnh_.advertise<needle_sim::TargetState>("target/state", 50);
  for (const auto& n : scene_.needles)
    wrench_pubs_.push_back(pnh_.advertise<geometry_msgs::WrenchStamped>(n.name + "/wrench", 1000));
  updater_ = std::make_unique<diagnostic_updater::Updater>(nh_, pnh_);
  updater_->setHardwareID("needle_sim/" + scene_.name);
  updater_->add("simulation", this, &SimulatorRos::diagnose);
  updater_->add("tip_speed", this, &SimulatorRos::diagnoseTipSpeed);
  diag_timer_ = nh_.createTimer(ros::Duration(1.0), [this](const ros::TimerEvent&) {
    std::lock_guard<PiMutex> lk(diag_mutex_);
    if (!diag_stopped_) updater_->update();
  });
  subscribeCommands();
  if (!P.assimilation.keys.empty()) {
    // The refits follow the base poses the needle took unless it follows the scene's motion,
    // at speeds up to the ceilings: what the live run took (within the limits of the time,
    // reconfigured or not) is taken again, never slowed.
    CommandLimits replay = guard().limits();
    for (const CeiledLimit& c : kCeiledLimits) replay.*c.limit = P.ceilings.*c.ceiling;
    replay.command_latency = 0;  // each pose is stamped when the base was there
    assimilation_ = std::make_unique<NodeAssimilation>(
        pnh_, P.assimilation, P.scene_file, P.overrides, scene_, P.command_source != "scene", replay,
        *tf_buffer_, P.tissue_frame, P.allow_empty_frame,
        [this](const ros::Time& t) {
          std::lock_guard<PiMutex> lk(queue_mutex_);
          return simSeconds(t);
        },
        [this](double t) {
          std::lock_guard<PiMutex> lk(queue_mutex_);
          return origin_.isZero() ? ros::Time::now() : origin_ + ros::Duration(t);
        });
    updater_->add("assimilation", assimilation_.get(), &NodeAssimilation::diagnose);
    ROS_INFO("needle_sim: assimilating measurements into %zu key(s), an estimate every %g s", P.assimilation.keys.size(),
             P.assimilation.every);
  }
  reset_srv_ = pnh_.advertiseService("reset", &SimulatorRos::onReset, this);
  set_target_srv_ = pnh_.advertiseService("set_target", &SimulatorRos::onSetTarget, this);
  {
    ros::AdvertiseServiceOptions o = ros::AdvertiseServiceOptions::create<needle_sim::PredictInsertion>(
        "predict",
        [this](needle_sim::PredictInsertion::Request& q, needle_sim::PredictInsertion::Response& r) {
          return onPredict(q, r);
        },
        ros::VoidConstPtr(), &predict_queue_);
    predict_srv_ = pnh_.advertiseService(o);
    // ~steer with the caller's id: an executed plan is that caller's command (rule owner).
    using SteerEvent = ros::ServiceEvent<needle_sim::SteerToTarget::Request, needle_sim::SteerToTarget::Response>;
    ros::AdvertiseServiceOptions so;
    so.initBySpecType<SteerEvent>("steer", [this](SteerEvent& e) {
      needle_sim::SteerToTarget::Request q = e.getRequest();
      return onSteer(q, e.getResponse(), e.getCallerName());
    });
    so.callback_queue = &predict_queue_;
    steer_srv_ = pnh_.advertiseService(so);
    // Two threads: a newer request starts at once and supersedes the one under way
    // (~predict_preempt); they take turns at the simulation (predict_turn_mutex_).
    predict_spinner_ = std::make_unique<ros::AsyncSpinner>(2, &predict_queue_);
    predict_spinner_->start();
  }
  action_ = std::make_unique<InsertAction>(*this, pnh_, P.insert_speed);
  reconfigure_ = std::make_unique<LimitsReconfigure>(pnh_, guard(), [this](double rate) { display_->setRate(rate); });
  if (P.target_error_period > 0) error_thread_ = std::thread(&SimulatorRos::errorLoop, this);
  // On the wall clock without tf commands the stepping thread keeps its own time; under
  // /use_sim_time (a bag's clock) or with tf lookups each tick, the timer drives it.
  self_paced_ = !P.as_fast_as_possible && !ros::Time::isSimTime() && base_frames_.empty();
  thread_ = self_paced_ ? std::thread(&SimulatorRos::pacedWorker, this) : std::thread(&SimulatorRos::worker, this);
  if (self_paced_ && P.wrench_rate > 0 && 1 / P.wrench_rate < scene_.dt) {
    wrench_period_ = 1 / P.wrench_rate;
    wrench_thread_ = std::thread(&SimulatorRos::wrenchLoop, this);
  }
  if (!P.as_fast_as_possible && !self_paced_)
    timer_ = nh_.createTimer(ros::Duration(scene_.dt), &SimulatorRos::onTimer, this);
  ROS_INFO("needle_sim: scene '%s' (%s), %d DOFs, dt %g s, commands from %s, interface under %s", scene_.name.c_str(),
           P.scene_file.c_str(), sim_->numDofs(), scene_.dt, P.command_source.c_str(), pnh_.getNamespace().c_str());
}

SimulatorRos::~SimulatorRos() {
  // No callback may start while the threads it would touch are joined and members go.
  reset_srv_.shutdown();
  set_target_srv_.shutdown();
  for (auto& sub : command_subs_) sub.shutdown();
  {
    std::lock_guard<PiMutex> lk(diag_mutex_);
    diag_stopped_ = true;
  }
  diag_timer_.stop();
  predict_srv_.shutdown();
  steer_srv_.shutdown();
  ++predict_epoch_;  // a prediction under way stops at its next step
  if (predict_spinner_) predict_spinner_->stop();  // waits for it
  timer_.stop();
  reconfigure_.reset();
  if (action_) action_->shutdown();
  {
    std::lock_guard<PiMutex> lk(queue_mutex_);
    stop_ = true;
  }
  wake_.notify_all();
  if (thread_.joinable()) thread_.join();
  {
    std::lock_guard<PiMutex> lk(wrench_mutex_);
    wrench_stop_ = true;
  }
  wrench_cv_.notify_all();
  if (wrench_thread_.joinable()) wrench_thread_.join();
  // Its subscriptions and its thread, once the stepping thread (which feeds it every step) and
  // the diagnostics (which read it) are done (found by ThreadSanitizer: the node-threads test).
  assimilation_.reset();
  {
    std::lock_guard<PiMutex> lk(error_mutex_);
    error_stop_ = true;
  }
  error_cv_.notify_all();
  if (error_thread_.joinable()) error_thread_.join();
  // The output thread runs queued jobs that hold the display and the action's goals: it sends
  // what is queued and stops before they go (found by ThreadSanitizer: the node-threads test).
  out_.reset();
  action_.reset();
  display_.reset();
}

void SimulatorRos::load() {
  Simulation::Options so;
  so.target_errors = params_->target_error_period > 0;
  sim_ = std::make_unique<Simulation>(scene_, so);
  {
    std::lock_guard<PiMutex> lk(error_mutex_);
    errors_latest_.clear();
    errors_step_ = -1;
  }
  last_error_time_ = -1e300;
  wrench_models_.clear();  // a new scene: no slope from the old one's last step
  {
    std::lock_guard<PiMutex> lk(wrench_mutex_);
    wrench_table_.ticks.clear();
    wrench_table_.step.clear();
  }
  names_ = std::make_shared<const ObservableNames>(observableNames(*sim_));
  if (!pipeline_) {
    pipeline_ = std::make_unique<CommandPipeline>(*sim_, params_->limits, params_->ceilings, "~");
    // The scene's own motion is not a command: new limits do not slow it.
    pipeline_->enforceOnMotion(params_->command_source != "scene");
  } else {
    pipeline_->restart(*sim_);
  }
  {
    std::lock_guard<PiMutex> lk(queue_mutex_);
    origin_ = ros::Time(0);  // restarted by the next tick
  }
  failure_.clear();
  tip_speed_.reset();
  tip_speed_.observe(*sim_);  // the tips at the start: the first step is measured from them
  commanded_ = false;
  primary_target_ = 0;
  step_ms_ = RunStatistics(1e3 * sim_->dt(), kStepWindow);
  rtf_window_.clear();
  observe(*sim_, obs_);
}

double SimulatorRos::simSeconds(const ros::Time& t) const {
  if (params_->as_fast_as_possible || origin_.isZero()) return sim_time_now_;
  return (t - origin_).toSec();
}

void SimulatorRos::restartClock(const ros::Time& now) {
  origin_ = now;
  schedule_.start(0.0);
}

// The simulation follows ROS time (the wall clock, or /clock under /use_sim_time): at each
// tick the schedule says how many steps are due since step 0, whatever the tick rate, so a
// bag replayed with --clock gives the same steps as the recording. A clock that jumps back
// (a bag played in a loop) restarts the scene.
void SimulatorRos::onTimer(const ros::TimerEvent&) {
  const ros::Time now = ros::Time::now();
  if (now.isZero()) return;  // sim time before the first /clock
  if (!base_frames_.empty()) lookupTfCommands();
  bool restart = false;
  {
    std::lock_guard<PiMutex> lk(queue_mutex_);
    if (origin_.isZero()) restartClock(now);
    const long due = schedule_.tick((now - origin_).toSec());
    if (due < 0) restart = true;
    if (due == 0) return;
  }
  if (restart) {
    restartAfterClockJump("time jumped back (bag loop?)");
    return;
  }
  wake_.notify_one();
}

void SimulatorRos::restartAfterClockJump(const char* what) {
  ROS_WARN("needle_sim: %s: the scene restarts", what);
  std_srvs::Trigger::Request req;
  std_srvs::Trigger::Response res;
  onReset(req, res);
}

int SimulatorRos::steppingPriority() const {
  // Not when stepping back to back (~as_fast_as_possible) unless asked for: a FIFO thread that
  // never sleeps holds its core for all but the kernel's real-time throttling share.
  const int p = params_->realtime_priority;
  if (p == 0 || (p < 0 && params_->as_fast_as_possible)) return 0;
  return p < 0 ? NodeParameters::kAutoRealtimePriority : p;
}

void SimulatorRos::setStepperPriority() {
  nameThisThread("ns_step");
  flushDenormalsToZero();  // as the tool's steps (inherited from main in the node; a nodelet's thread sets it here)
  const bool automatic = params_->realtime_priority < 0;
  const int prio = steppingPriority();
  if (prio == 0) return;
  sched_param sp{};
  sp.sched_priority = prio;
  const int err = pthread_setschedparam(pthread_self(), SCHED_FIFO, &sp);
  realtime_priority_ = err == 0 ? prio : 0;
  if (err == 0) waitedForWorkNice() = 0;  // background_priority.hpp
  if (err == 0)
    ROS_INFO("needle_sim: stepping thread on SCHED_FIFO priority %d%s", prio, automatic ? " (~realtime_priority: -1)" : "");
  else if (automatic)
    ROS_INFO("needle_sim: the stepping thread runs on the default scheduler (SCHED_FIFO not permitted: %s; grant "
             "CAP_SYS_NICE or an rtprio limit for steps that other threads cannot delay)", std::strerror(err));
  else
    ROS_WARN("needle_sim: ~realtime_priority %d: cannot take SCHED_FIFO (%s); the stepping thread runs on the default "
             "scheduler (grant CAP_SYS_NICE or an rtprio limit)", prio, std::strerror(err));
}

void SimulatorRos::leaveRealtimePriority(double behind) {
  // Only the automatic priority: an explicit one is the deployment's decision.
  if (realtime_priority_ == 0 || params_->realtime_priority > 0) return;
  sched_param none{};
  if (pthread_setschedparam(pthread_self(), SCHED_OTHER, &none) != 0) return;
  realtime_priority_ = 0;
  waitedForWorkNice() = 10;
  ROS_WARN("needle_sim: the simulation is %.1f s behind the clock: it does not keep real time here, and the stepping "
           "thread, stepping back to back, leaves SCHED_FIFO (~realtime_priority -1) so as not to hold a core",
           behind);
}

void SimulatorRos::worker() {
  setStepperPriority();
  const bool as_fast = params_->as_fast_as_possible;
  for (;;) {
    {
      std::unique_lock<PiMutex> lk(queue_mutex_);
      wake_.wait(lk, [&] { return stop_ || as_fast || schedule_.pending() > 0; });
      if (stop_) return;
      if (!as_fast) schedule_.takeStep();
    }
    std::lock_guard<PiMutex> lk(sim_mutex_);
    applyCommands();
    stepOnce();
  }
}

void SimulatorRos::pacedWorker() {
  setStepperPriority();
  for (;;) {
    bool back = false;
    {
      std::unique_lock<PiMutex> lk(queue_mutex_);
      if (stop_) return;
      const ros::Time now = ros::Time::now();
      if (origin_.isZero()) restartClock(now);
      back = schedule_.tick((now - origin_).toSec()) < 0;
    }
    if (back) {  // the system clock was set back: as a bag loop under the timer, a restart
      restartAfterClockJump("the clock went back");
      continue;
    }
    // The due steps (several after a stall: back to back, each counted late if it is).
    for (;;) {
      {
        std::lock_guard<PiMutex> lk(queue_mutex_);
        if (stop_) return;
        if (!schedule_.takeStep()) break;
      }
      std::lock_guard<PiMutex> lk(sim_mutex_);
      applyCommands();
      stepOnce();
    }
    std::unique_lock<PiMutex> lk(queue_mutex_);
    if (origin_.isZero()) continue;  // restarted (~reset): the clock starts again now
    const double wait = schedule_.nextDue() - (ros::Time::now() - origin_).toSec();
    if (wait > 0) wake_.wait_for(lk, std::chrono::duration<double>(wait), [&] { return stop_; });
  }
}

void SimulatorRos::applyCommands() {
  for (const CommandPipeline::Event& e : pipeline_->beforeStep(*sim_)) {
    const std::string& needle = names_->needles[e.needle];
    switch (e.kind) {
      case CommandPipeline::Event::Kind::Taken:
        // A command or a plan of another sender supersedes an ~insert goal on the needle.
        if (action_ && !e.has_done) action_->superseded(e.needle, e.source);
        commanded_ = true;
        break;
      case CommandPipeline::Event::Kind::Limited:
        warnRule(e.rule, needle + " command", e.why);
        break;
      case CommandPipeline::Event::Kind::Refused:
        warnRule(e.rule, e.source, e.why);
        break;
      case CommandPipeline::Event::Kind::Enforced:
        ROS_INFO("needle_sim: %s: the motion under way slowed down to the new limits", needle.c_str());
        break;
    }
  }
}

void SimulatorRos::errorLoop() {
  nameThisThread("ns_target_err");
  flushDenormalsToZero();
  // Nothing waits for an estimate (the outputs carry the latest finished one): below every
  // other thread, so that on two cores it takes neither the stepping thread's core nor the
  // background factor refreshes' (a stale factor costs the step CG iterations).
  idleThisThread();
  for (;;) {
    std::unique_ptr<Simulation> job;
    {
      std::unique_lock<PiMutex> lk(error_mutex_);
      error_cv_.wait(lk, [&] { return error_stop_ || error_job_; });
      if (error_stop_) return;
      job = std::move(error_job_);
    }
    std::vector<TargetError> errs;
    const auto t0 = std::chrono::steady_clock::now();
    try {
      errs = job->targetErrors();
    } catch (const std::exception& e) {
      ROS_WARN_THROTTLE(10.0, "needle_sim: target error estimate failed: %s", e.what());
    }
    for (auto& e : errs) e.indicator.clear();  // (not needed here)
    // An estimate that took w of wall time is followed by w (1 / duty - 1) without one: on
    // two cores an estimate running back to back (the DBS scenes' take longer than their
    // period) slowed the stepping thread beside it by about half even at SCHED_IDLE
    // (doc/benchmarks.md, "Bounded step time").
    const auto t1 = std::chrono::steady_clock::now();
    const auto rest = std::chrono::duration_cast<std::chrono::steady_clock::duration>(
        (t1 - t0) * (1.0 / params_->target_error_duty - 1.0));
    std::lock_guard<PiMutex> lk(error_mutex_);
    next_error_wall_ = t1 + rest;
    const double w = std::chrono::duration<double>(t1 - t0).count();
    ++error_estimates_;
    error_wall_s_total_ += w;
    error_wall_s_max_ = std::max(error_wall_s_max_, w);
    if (!errs.empty()) {
      errors_latest_ = std::move(errs);
      errors_step_ = job->stepIndex();
    }
    error_busy_ = false;
  }
}

void SimulatorRos::updateTargetErrors() {
  if (!(params_->target_error_period > 0) || sim_->numTargets() == 0) return;
  // With goal-oriented adaptivity the simulation estimates on its own passes.
  if (sim_->adaptation() && sim_->adaptation()->settings().estimator == AdaptivitySettings::Estimator::Goal) return;
  {
    std::lock_guard<PiMutex> lk(error_mutex_);
    // The copy is taken on this thread between steps: not while background work it would wait
    // for is under way (a factor refresh: up to 23 ms on the DBS scene), a step later instead.
    if (!error_busy_ && sim_->time() - last_error_time_ >= params_->target_error_period - 1e-12 &&
        std::chrono::steady_clock::now() >= next_error_wall_ && !sim_->backgroundWorkRunning()) {
      last_error_time_ = sim_->time();
      error_busy_ = true;
      error_job_ = std::make_unique<Simulation>(*sim_);
      error_cv_.notify_one();
    }
    if (errors_latest_.size() != obs_.targets.size()) return;
    for (size_t i = 0; i < errors_latest_.size(); ++i) {
      TargetObservation& t = obs_.targets[i];
      const TargetError& e = errors_latest_[i];
      t.has_error = e.valid;
      t.error_step = errors_step_;
      t.error = e.estimate;
      t.error_bound = e.bound;
      t.qoi = e.qoi;
    }
  }
}

void SimulatorRos::queuePlan(Plan plan) { pipeline_->submitPlan(std::move(plan)); }

void SimulatorRos::holdNeedle(int needle) { pipeline_->hold(needle); }

void SimulatorRos::stepOnce() {
  double ms = 0;
  if (failure_.empty()) {
    const auto t0 = ros::WallTime::now();
    try {
      const StepStats& s = sim_->step();
      unconverged_steps_ += s.constraint_converged ? 0 : 1;
      constraint_residual_ = s.constraint_residual;
      watchTipSpeed();
    } catch (const NumericalError& e) {
      failure_ = e.what();
      {
        std::lock_guard<PiMutex> lk(wrench_mutex_);
        wrench_table_.ticks.clear();  // nothing more between steps
        wrench_table_.step.clear();
      }
      ROS_ERROR("needle_sim: numerical failure, stepping stopped until ~reset: %s", e.what());
    }
    ms = (ros::WallTime::now() - t0).toSec() * 1e3;
    step_ms_.add(ms);
    sim_time_now_ = sim_->time();
    if (!params_->as_fast_as_possible) {
      const ros::Time end = ros::Time::now();
      double behind = 0;
      {
        std::lock_guard<PiMutex> lk(queue_mutex_);
        if (!origin_.isZero()) {
          schedule_.stepDone(sim_->stepIndex(), (end - origin_).toSec());
          behind = (end - origin_).toSec() - sim_->time();
        }
      }
      if (behind > kFifoMaxLag) leaveRealtimePriority(behind);
    }
  }
  const auto p0 = ros::WallTime::now();
  publishStep(ms);
  publish_ms_ = (ros::WallTime::now() - p0).toSec() * 1e3;
}

double SimulatorRos::maxTipSpeed() const {
  return params_->max_tip_speed > 0 ? params_->max_tip_speed : 4 * guard().limits().max_speed;
}

void SimulatorRos::watchTipSpeed() {
  tip_speed_.observe(*sim_);
  const double limit = maxTipSpeed();
  for (int n = 0; n < tip_speed_.numNeedles(); ++n) {
    const double v = tip_speed_.speed(n);
    tip_speed_peak_[n] = std::max(tip_speed_peak_[n], v);
    if (!(v > limit)) continue;
    ++tip_speed_over_[n];
    // Throttled as the guard's rules: at most one message a second, the next says how many
    // it stood for; but a speed twice that of the last message is told at once (a snap-back
    // grows over a few steps: its peak must not hide behind the first step over the limit).
    const ros::WallTime w = ros::WallTime::now();
    if (!last_tip_warning_.isZero() && (w - last_tip_warning_).toSec() < 1.0 && !(v > 2 * last_tip_warned_speed_)) {
      ++tip_warnings_suppressed_;
      continue;
    }
    last_tip_warning_ = w;
    last_tip_warned_speed_ = v;
    const unsigned long more = tip_warnings_suppressed_;
    tip_warnings_suppressed_ = 0;
    const Vec3 tip = sim_->needle(n).tipPosition();
    ROS_WARN("needle_sim: %s: the tip moved at %.3g m/s over the step to t = %.4f s, faster than ~max_tip_speed = "
             "%g m/s (the guard limits the base; a needle bent in the tissue snaps back as it leaves it), tip now "
             "(%.4g, %.4g, %.4g) m%s",
             names_->needles[n].c_str(), v, sim_->time(), limit, tip.x(), tip.y(), tip.z(),
             more ? (" (and " + std::to_string(more) + " more steps since the last message)").c_str() : "");
  }
}

void SimulatorRos::diagnoseTipSpeed(diagnostic_updater::DiagnosticStatusWrapper& stat) {
  std::lock_guard<PiMutex> lk(sim_mutex_);
  const double limit = maxTipSpeed();
  std::string warn;
  stat.add("max_tip_speed", limit);
  for (int n = 0; n < static_cast<int>(tip_speed_peak_.size()); ++n) {
    const std::string& name = names_->needles[n];
    if (tip_speed_over_[n] > diag_tip_over_[n]) {
      char b[240];
      std::snprintf(b, sizeof b, "%s: tip at up to %.3g m/s, above ~max_tip_speed = %g m/s (%lu steps since the last "
                    "report)", name.c_str(), tip_speed_peak_[n], limit,
                    static_cast<unsigned long>(tip_speed_over_[n] - diag_tip_over_[n]));
      warn += (warn.empty() ? "" : "; ") + std::string(b);
    }
    stat.addf(name + "/tip_speed", "%.9g", tip_speed_.numNeedles() > n ? tip_speed_.speed(n) : 0.0);
    stat.addf(name + "/tip_speed_peak", "%.9g", tip_speed_peak_[n]);
    stat.add(name + "/tip_speed_over_limit_steps", tip_speed_over_[n]);
    diag_tip_over_[n] = tip_speed_over_[n];
    tip_speed_peak_[n] = 0;
  }
  if (warn.empty())
    stat.summary(diagnostic_msgs::DiagnosticStatus::OK, "tips within ~max_tip_speed");
  else
    stat.summary(diagnostic_msgs::DiagnosticStatus::WARN, warn);
}

}  // namespace needle_sim

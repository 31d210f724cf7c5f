// SimulatorRos: what every step sends (status, wrenches, targets; built on the output
// thread from a StepFrame of numbers), the display outputs at their rate, and diagnostics.
#include <geometry_msgs/PointStamped.h>
#include <geometry_msgs/WrenchStamped.h>
#include <needle_sim/SimStatus.h>
#include <needle_sim/TargetState.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>

#include "conversions.hpp"
#include "needle_sim/core/background_priority.hpp"
#include "node_assimilation.hpp"
#include "display_outputs.hpp"
#include "insert_action.hpp"
#include "limits_reconfigure.hpp"
#include "needle_sim/ros/simulator_ros.hpp"
#include "node_parameters.hpp"
#include "output_queue.hpp"

namespace needle_sim {

void SimulatorRos::publishStep(double ms) {
  const ros::WallTime wall = ros::WallTime::now();
  rtf_window_.emplace_back(wall, sim_->time());
  while (rtf_window_.size() > 2 && (wall - rtf_window_.front().first).toSec() > 1.0) rtf_window_.pop_front();
  StepFrame f;
  f.stamp = ros::Time::now();
  f.names = names_;
  f.failure = failure_;
  f.state = !failure_.empty() ? "failed" : (!commanded_ && params_->command_source != "scene") ? "waiting" : "running";
  f.step_ms = ms;
  f.step_ms_max = step_ms_.max();
  f.publish_ms = publish_ms_;
  const double dw = (rtf_window_.back().first - rtf_window_.front().first).toSec();
  f.rtf = dw > 0 ? (rtf_window_.back().second - rtf_window_.front().second) / dw : 0.0;
  {
    std::lock_guard<PiMutex> lk(queue_mutex_);
    const double clock = origin_.isZero() ? 0.0 : (f.stamp - origin_).toSec();
    f.deadlines = schedule_.counts(clock);
    if (!params_->as_fast_as_possible && !origin_.isZero()) f.lag = std::max(0.0, clock - sim_->time());
  }
  f.guard = guard().counts();
  f.rejected = guard().rejected();
  f.clamped = guard().limited();
  f.unconverged = unconverged_steps_;
  f.constraint_residual = constraint_residual_;
  f.display_range = display_->range();
  if (failure_.empty()) {  // never publish a state that failed: the status alone
    observe(*sim_, obs_);
    if (wrench_period_ > 0) tabulateWrenches(f.stamp);
    updateTargetErrors();
    f.obs = obs_;
    f.primary_target = std::min(primary_target_, sim_->numTargets() - 1);
    f.send_target_point = sim_->numTargets() > 0 && target_pub_.getNumSubscribers() > 0;
    f.send_target_state = sim_->numTargets() > 0 && target_state_pub_.getNumSubscribers() > 0;
    if (action_) action_->update(obs_);
    if (assimilation_) {
      assimilation_->afterStep(*sim_, obs_);
      if (f.send_target_state) f.predictions = assimilation_->predictions();
    }
  } else {
    f.obs.step = sim_->stepIndex();
    f.obs.time = sim_->time();
    f.obs.dofs = sim_->numDofs();
    if (action_) action_->abort("numerical failure: " + failure_);
  }
  out_->post([this, f = std::move(f)] { sendStep(f); });
  if (!failure_.empty()) return;
  if ((wall - last_display_).toSec() >= 1.0 / display_->rate()) {
    last_display_ = wall;
    display_->publish(*sim_, names_, primary_target_, obs_,
                      assimilation_ ? assimilation_->predictions() : std::vector<TargetPrediction>{});
  }
}

void SimulatorRos::tabulateWrenches(const ros::Time& stamp) {
  // The models follow every step (a slope needs the step before); the table only when heard.
  wrench_models_.resize(obs_.needles.size());
  const double t0 = sim_->time();
  for (size_t i = 0; i < obs_.needles.size(); ++i) {
    const NeedleObservation& n = obs_.needles[i];
    wrench_models_[i].afterStep(sim_->needle(static_cast<int>(i)).trajectory().pose(t0).position, n.holder_force,
                                n.holder_moment, n.constraints);
  }
  bool heard = false;
  for (const auto& pub : wrench_pubs_) heard = heard || pub.getNumSubscribers() > 0;
  WrenchTable table;
  table.stamp = stamp;
  if (heard && wrench_pubs_.size() == obs_.needles.size()) {
    const bool in_base = params_->wrench_frame == "base";
    auto frame = [&](size_t i, const Vec3& f, const Vec3& m) {  // as wrenchMessage: the base frame of observables.cpp
      const Eigen::Quaterniond to_base = obs_.needles[i].base_frame.conjugate();
      return std::make_pair(in_base ? Vec3(to_base * f) : f, in_base ? Vec3(to_base * m) : m);
    };
    for (size_t i = 0; i < obs_.needles.size(); ++i) {
      table.frames.push_back(in_base ? names_->needles[i] + "_base" : params_->tissue_frame);
      table.step.push_back(frame(i, obs_.needles[i].holder_force, obs_.needles[i].holder_moment));
    }
    const int ticks = static_cast<int>(std::ceil(2 * sim_->dt() / wrench_period_ - 1e-9));
    table.ticks.resize(ticks);
    for (int j = 1; j <= ticks; ++j)
      for (size_t i = 0; i < obs_.needles.size(); ++i) {
        Vec3 f, m;
        wrench_models_[i].at(sim_->needle(static_cast<int>(i)).trajectory().pose(t0 + j * wrench_period_).position, f, m);
        table.ticks[j - 1].push_back(frame(i, f, m));
      }
  }
  {
    std::lock_guard<PiMutex> lk(wrench_mutex_);
    table.seq = wrench_table_.seq + 1;
    table.made = std::chrono::steady_clock::now();
    wrench_table_ = std::move(table);
  }
  wrench_cv_.notify_one();
}

void SimulatorRos::wrenchLoop() {
  nameThisThread("ns_wrench");
  // Never before the stepping thread (background_priority.hpp): on two cores, at nice 0 or
  // 10, the stream made 5-8 % of the gel demo's steps late with 500 Hz poses and every output
  // subscribed (0.3-0.7 % without it); idle, it takes what a core leaves. With the stepping
  // thread at SCHED_FIFO, the stream is real-time output too: just below it. (Idle, it held
  // the step's hand-over, whose condition variable's own mutex has no priority inheritance,
  // for milliseconds while any other thread ran.)
  const int stepping = steppingPriority();
  sched_param sp{};
  sp.sched_priority = std::max(1, stepping - 1);
  if (stepping == 0 || pthread_setschedparam(pthread_self(), SCHED_FIFO, &sp) != 0) idleThisThread();
  using clock = std::chrono::steady_clock;
  const auto period = std::chrono::duration_cast<clock::duration>(std::chrono::duration<double>(wrench_period_));
  auto next = clock::now() + period;
  clock::time_point step_sent;
  long sent = 0;      // the table whose step row went out
  ros::Time last;     // the last stamp sent
  ros::Time stamp;
  for (;;) {
    std::vector<std::string> frames;
    std::vector<std::pair<Vec3, Vec3>> row;
    {
      std::unique_lock<PiMutex> lk(wrench_mutex_);
      auto woken = [&] { return wrench_stop_ || wrench_table_.seq != sent; };
      bool step = true;
      if (wrench_table_.ticks.empty())  // nobody listens (or a failure): no tick to send, none to wake for
        wrench_cv_.wait(lk, woken);
      else
        step = wrench_cv_.wait_until(lk, next, woken);
      if (wrench_stop_) return;
      const WrenchTable& w = wrench_table_;
      const auto now = clock::now();
      if (step) {  // a step: its own wrench, at once, stamped as its status
        sent = w.seq;
        step_sent = now;
        row = w.step;
        stamp = w.stamp;
      } else {
        next += period;
        if (next < now) next = now + period;  // after a stall: on, not a burst
        if (now - step_sent < period / 2) continue;  // a step's row just went
        // The row of the time since the step was tabulated; none past two steps (stalled).
        const long j = std::lround(std::chrono::duration<double>(now - w.made) / std::chrono::duration<double>(period));
        if (j < 1 || j > static_cast<long>(w.ticks.size())) continue;
        stamp = w.stamp + ros::Duration(static_cast<double>(j) * wrench_period_);
        if (stamp <= last) continue;  // in order
        row = w.ticks[j - 1];
      }
      frames = w.frames;
    }
    last = std::max(last, stamp);
    for (size_t i = 0; i < row.size() && i < wrench_pubs_.size(); ++i) {
      geometry_msgs::WrenchStamped m;
      m.header.stamp = stamp;
      m.header.frame_id = frames[i];
      m.wrench.force = toVector(row[i].first);
      m.wrench.torque = toVector(row[i].second);
      wrench_pubs_[i].publish(m);
    }
  }
}

void SimulatorRos::sendStep(const StepFrame& f) {
  status_pub_.publish(statusMessage(f, params_->tissue_frame));
  if (!f.failure.empty()) return;
  if (wrench_period_ == 0)  // else wrenchLoop sends them, between the steps too
    for (size_t i = 0; i < f.obs.needles.size(); ++i)
      wrench_pubs_[i].publish(wrenchMessage(f, static_cast<int>(i), params_->wrench_frame == "base", params_->tissue_frame));
  if (f.send_target_point) {
    geometry_msgs::PointStamped ps;
    ps.header.stamp = f.stamp;
    ps.header.frame_id = params_->tissue_frame;
    ps.point = toPoint(f.obs.targets[f.primary_target].position);
    target_pub_.publish(ps);
  }
  if (f.send_target_state)
    for (auto& m : targetStates(f, params_->tissue_frame)) target_state_pub_.publish(m);
}

void SimulatorRos::diagnose(diagnostic_updater::DiagnosticStatusWrapper& stat) {
  std::unique_lock<PiMutex> lk(sim_mutex_);
  // The recent step times, copied under the lock and sorted after it (a sort of 10,000 under
  // it would delay a 1 kHz step).
  std::vector<double> recent = step_ms_.samples();
  const auto counts = guard().counts();
  const uint64_t rej = guard().rejected(), lim = guard().limited();
  RealtimeSchedule::Counts d;
  {
    std::lock_guard<PiMutex> q(queue_mutex_);
    d = schedule_.counts(origin_.isZero() ? 0.0 : (ros::Time::now() - origin_).toSec());
  }
  const double warn = params_->deadline_warn_fraction;
  const double lag = origin_.isZero() || params_->as_fast_as_possible
                         ? 0.0
                         : std::max(0.0, (ros::Time::now() - origin_).toSec() - sim_->time());
  // Every condition that holds is named; the level is the worst of them. Slow-downs to the
  // speed limits are the guard doing its work (counted, not warned).
  std::vector<std::string> warnings;
  if (rej > diag_rejected_) warnings.push_back(std::to_string(rej - diag_rejected_) + " commands rejected");
  if (d.late_fraction > warn || d.skipped_fraction > warn) {
    char b[200];
    std::snprintf(b, sizeof b, "not keeping real time: %.1f %% of the last second's steps late, %.1f %% of its ticks "
                  "skipped (~deadline_warn_fraction %.1f %%)", 100 * d.late_fraction, 100 * d.skipped_fraction, 100 * warn);
    warnings.push_back(b);
  }
  if (reconfigure_ && !reconfigure_->lastRefusal().empty())
    warnings.push_back("the last reconfigure was refused: " + reconfigure_->lastRefusal());
  if (unconverged_steps_ > diag_unconverged_)
    warnings.push_back(std::to_string(unconverged_steps_ - diag_unconverged_) +
                       " steps since the last report whose needle-tissue constraint solve missed its tolerance "
                       "(interaction.solver; last residual " + std::to_string(constraint_residual_) + ")");
  if (lag > 10 * scene_.dt) warnings.push_back("the simulation is " + std::to_string(lag) + " s behind the clock");
  if (preflight_run_ && !preflight_.keepsRealTime())
    warnings.push_back("the pre-flight says this scene will not keep real time here (margin " +
                       std::to_string(preflight_.margin()) + ", ~preflight_wall)");
  if (!failure_.empty()) {
    stat.summary(diagnostic_msgs::DiagnosticStatus::ERROR, "numerical failure: " + failure_);
  } else if (!warnings.empty()) {
    std::string m;
    for (const auto& w : warnings) m += (m.empty() ? "" : "; ") + w;
    stat.summary(diagnostic_msgs::DiagnosticStatus::WARN, m);
  } else {
    stat.summary(diagnostic_msgs::DiagnosticStatus::OK, commanded_ || params_->command_source == "scene" ? "running"
                                                                                                : "waiting for commands");
  }
  stat.add("lag_s", lag);
  stat.add("reconfigure_refused", reconfigure_ ? reconfigure_->refusals() : 0UL);
  stat.add("slowed_down_last_second", lim - diag_limited_);
  diag_rejected_ = rej;
  diag_limited_ = lim;
  stat.add("unconverged_steps", unconverged_steps_);
  diag_unconverged_ = unconverged_steps_;
  stat.add("scene", scene_.name);
  stat.add("step", sim_->stepIndex());
  stat.add("sim_time", sim_->time());
  stat.add("dofs", sim_->numDofs());
  stat.add("step_ms_max", step_ms_.max());  // since the start or ~reset
  stat.add("steps_over_dt", step_ms_.misses());
  stat.add("late_steps", d.late);
  stat.add("skipped_ticks", d.skipped);
  stat.add("late_steps_per_s", d.late_per_s);
  stat.add("skipped_ticks_per_s", d.skipped_per_s);
  stat.add("longest_late_run", d.longest_late_run);
  stat.add("rejected_commands", rej);
  stat.add("clamped_commands", lim);
  for (int r = 0; r < kGuardRules; ++r) stat.add(std::string("guard/") + ruleName(static_cast<GuardRule>(r)), counts[r]);
  stat.add("output_thread_ms_total", out_->busyMs());
  stat.add("output_messages_dropped", out_->dropped());
  lk.unlock();
  const Percentiles sp = percentiles(std::move(recent));
  stat.add("step_ms_median", sp.median);  // of the last kStepWindow steps
  stat.add("step_ms_p999", sp.p999);
  // ~predict and ~steer requests: how many, how many stopped by ~predict_max_wall or
  // cancelled, and their wall time (each on the predictions' own low-priority thread).
  std::lock_guard<std::mutex> pk(predict_cost_mutex_);
  const PredictionCost& c = predict_cost_;
  stat.add("predictions", c.requests);
  stat.add("predictions_stopped", c.stopped);
  stat.add("predictions_cancelled", c.cancelled);
  stat.add("predictions_preempted", c.preempted);
  stat.add("prediction_wall_s_last", c.last_s);
  stat.add("prediction_wall_s_max", c.max_s);
  stat.add("prediction_wall_s_total", c.total_s);
  // The targets' live error estimates (~target_error_period, ~target_error_duty): how many,
  // their wall time.
  {
    std::lock_guard<PiMutex> ek(error_mutex_);
    stat.add("stepping_thread", realtime_priority_ > 0 ? "SCHED_FIFO " + std::to_string(realtime_priority_.load())
                                                       : std::string("default scheduler"));
    stat.add("target_error_estimates", error_estimates_);
    stat.add("target_error_wall_s_total", error_wall_s_total_);
    stat.add("target_error_wall_s_max", error_wall_s_max_);
  }
  // The pre-flight at start (~preflight_wall): its verdict and figures.
  if (preflight_run_) {
    const PreflightResult& f = preflight_;
    stat.add("preflight", f.keepsRealTime() ? "keeps real time" : "will not keep real time");
    stat.add("preflight_margin", f.margin());
    stat.add("preflight_steps", f.steps);
    stat.add("preflight_sim_time_s", f.t_end);
    stat.add("preflight_step_ms_median", f.median_ms);
    stat.add("preflight_step_ms_p999", f.p999_ms);
    stat.add("preflight_step_ms_max", f.max_ms);
    stat.add("preflight_steps_over_dt", f.over_dt);
    stat.add("preflight_summary", f.summary());
  } else {
    stat.add("preflight", "not run (~preflight_wall 0)");
  }
}

}  // namespace needle_sim

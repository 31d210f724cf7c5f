// NodeAssimilation: measurements in, the online estimate out (node_assimilation.hpp).
#include "node_assimilation.hpp"

#include <needle_sim/ParameterEstimate.h>
#include <tf2/exceptions.h>

#include <algorithm>
#include <cmath>

#include "conversions.hpp"
#include "needle_sim/core/background_priority.hpp"
#include "needle_sim/core/denormals.hpp"
#include "needle_sim/core/error.hpp"
#include "needle_sim/sim/simulation.hpp"

namespace needle_sim {

namespace {
const char* const kRuleNames[] = {"non_finite", "frame", "stale", "future", "shape"};
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
}  // namespace

NodeAssimilation::NodeAssimilation(ros::NodeHandle pnh, const AssimilationParameters& p, const std::string& scene_file,
                                   const std::vector<std::string>& overrides, const Scene& scene, bool replay,
                                   const CommandLimits& limits, tf2_ros::Buffer& tf, const std::string& tissue_frame,
                                   bool allow_empty_frame, std::function<double(const ros::Time&)> sim_seconds,
                                   std::function<ros::Time(double)> ros_time)
    : p_(p),
      replay_(replay),
      tf_(tf),
      tissue_frame_(tissue_frame),
      allow_empty_frame_(allow_empty_frame),
      sim_seconds_(std::move(sim_seconds)),
      ros_time_(std::move(ros_time)) {
  const auto positive = [](double v) { return std::isfinite(v) && v > 0; };
  const auto given = [&](double v, const char* name) {
    if (std::isnan(v)) return false;
    if (!positive(v)) throw InputError("", name, "must be a positive number (a standard deviation)");
    return true;
  };
  const bool force = given(p.wrench_noise, "~assimilation/wrench_noise");
  const bool tip = given(p.tip_noise, "~assimilation/tip_noise");
  const bool target = given(p.target_noise, "~assimilation/target_noise");
  const bool shape = given(p.shape_noise, "~assimilation/shape_noise");
  if (!force && !tip && !target && !shape)
    throw InputError("", "~assimilation/keys",
                     "needs a measurement to estimate from: give the noise of at least one of ~assimilation/wrench_noise "
                     "[N], ~assimilation/tip_noise [m], ~assimilation/target_noise [m], ~assimilation/shape_noise [m]");
  if (shape && !(std::isfinite(p.shape_spacing) && p.shape_spacing > 0))
    throw InputError("", "~assimilation/shape_spacing", "must be a positive arc length [m]");
  if (!(p.every > 0)) throw InputError("", "~assimilation/every", "must be a positive time [s]");
  if (!(p.outlier_gate > 1)) throw InputError("", "~assimilation/outlier_gate", "must exceed 1 (noise standard deviations)");
  if (!(p.max_latency >= 0)) throw InputError("", "~assimilation/max_latency", "must be a time >= 0 [s]");
  needle_ = -1;
  for (size_t i = 0; i < scene.needles.size(); ++i)
    if (p.needle.empty() ? i == 0 : scene.needles[i].name == p.needle) needle_ = static_cast<int>(i);
  if (needle_ < 0) throw InputError("", "~assimilation/needle", "the scene has no needle '" + p.needle + "'");
  for (const auto& t : scene.targets) target_names_.push_back(t.name);
  scene_target_names_ = target_names_;
  num_targets_ = static_cast<int>(target_names_.size());
  target_ = -1;
  for (int j = 0; j < num_targets_; ++j)
    if (p.target.empty() ? j == 0 : target_names_[j] == p.target) target_ = j;
  if (target && target_ < 0)
    throw InputError("", "~assimilation/target", "the scene has no target '" + p.target + "' to measure");
  base_frame_ = scene.needles[needle_].name + "_base";
  channels_ = {force, tip, target, shape};
  needle_length_ = scene.needles[needle_].length;

  AssimilationSettings& s = settings_;
  s.fit.scene = scene_file;
  s.fit.sets = overrides;
  for (const std::string& k : p.keys) s.fit.parameters.push_back(CalibrationParameter{k});
  s.fit.needle = needle_;
  s.fit.noise = force ? p.wrench_noise : kNaN;
  s.fit.tip_noise = tip ? p.tip_noise : kNaN;
  s.fit.target_noise = target ? p.target_noise : kNaN;
  s.fit.shape_noise = shape ? p.shape_noise : kNaN;
  s.fit.threads = 1;  // one core is the live loop's
  s.fit.limits = limits;
  s.fit.cancel = &cancel_;
  s.every = p.every;
  s.outlier_gate = p.outlier_gate;
  try {
    (void)resolveParameters(s.fit);  // a key the scene lacks: refused at start
  } catch (const InputError& e) {
    throw InputError("", "~assimilation/keys", e.what());
  }
  units_ = force ? "N" : "m";
  if (!(p.adopt_ramp >= 0) || !std::isfinite(p.adopt_ramp))
    throw InputError("", "~assimilation/adopt_ramp", "must be a time >= 0 [s]");
  in_use_.assign(p.keys.size(), kNaN);
  if (p.adopt) {
    adoption_ = std::make_unique<ParameterAdoption>(p.keys, p.adopt_ramp);
    std::string kept;
    for (size_t i = 0; i < p.keys.size(); ++i)
      if (!adoption_->adoptable(static_cast<int>(i))) kept += (kept.empty() ? "" : ", ") + p.keys[i];
    if (!kept.empty())
      ROS_WARN("needle_sim: assimilation: %s estimated, not adopted: the live simulation takes only "
               "tissue.material.young and the interaction's cutting_force, puncture_force, friction and grip_pressure "
               "during a run",
               kept.c_str());
  }

  estimate_pub_ = pnh.advertise<needle_sim::ParameterEstimate>("estimate", 10, true);
  const std::string& name = scene.needles[needle_].name;
  if (force)
    subs_.push_back(pnh.subscribe<geometry_msgs::WrenchStamped>(
        name + "/measured_wrench", 100, [this](const geometry_msgs::WrenchStamped::ConstPtr& m) { onWrench(m); }));
  if (tip)
    subs_.push_back(pnh.subscribe<geometry_msgs::PointStamped>(
        name + "/measured_tip", 100,
        [this](const geometry_msgs::PointStamped::ConstPtr& m) { onPoint(1, "<needle>/measured_tip", m); }));
  if (target)
    subs_.push_back(pnh.subscribe<geometry_msgs::PointStamped>(
        "target/measured", 100,
        [this](const geometry_msgs::PointStamped::ConstPtr& m) { onPoint(2, "target/measured", m); }));
  if (shape)
    subs_.push_back(pnh.subscribe<geometry_msgs::PoseArray>(
        name + "/measured_shape", 100, [this](const geometry_msgs::PoseArray::ConstPtr& m) { onShape(m); }));
  next_due_ = p.every;
  thread_ = std::thread(&NodeAssimilation::worker, this);
}

NodeAssimilation::~NodeAssimilation() {
  for (auto& s : subs_) s.shutdown();
  {
    std::lock_guard<PiMutex> lk(mutex_);
    stop_ = true;
    cancel_ = true;  // a refit under way stops at its run's next step
  }
  wake_.notify_all();
  if (thread_.joinable()) thread_.join();
}

void NodeAssimilation::refuse(Rule r, const char* topic, const std::string& why) {
  const ros::WallTime now = ros::WallTime::now();
  long more = 0;
  {
    std::lock_guard<PiMutex> lk(mutex_);
    ++refused_[r];
    ros::WallTime& last = last_warning_[r];
    if (!last.isZero() && (now - last).toSec() < 1.0) {
      ++suppressed_[r];
      return;
    }
    last = now;
    more = suppressed_[r];
    suppressed_[r] = 0;
  }
  ROS_WARN("needle_sim: ~%s refused (%s): %s%s", topic, kRuleNames[r], why.c_str(),
           more ? (" (and " + std::to_string(more) + " more since the last message)").c_str() : "");
}

bool NodeAssimilation::admit(const std_msgs::Header& h, const char* topic, double& t, Rigid& to_tissue) {
  to_tissue = Rigid{};
  const std::string& frame = h.frame_id;
  if (frame.empty() && !allow_empty_frame_) {
    refuse(Frame, topic, "empty frame_id (set it to '" + tissue_frame_ + "', or allow it with ~allow_empty_frame)");
    return false;
  }
  if (!frame.empty() && frame != tissue_frame_ && frame != base_frame_) {
    try {
      to_tissue = fromTransform(tf_.lookupTransform(tissue_frame_, frame, ros::Time(0)).transform);
    } catch (const tf2::TransformException& e) {
      refuse(Frame, topic, "no transform " + tissue_frame_ + " <- '" + frame + "': " + e.what());
      return false;
    }
  }
  // Unstamped: measured when it arrived.
  t = sim_seconds_(h.stamp.isZero() ? ros::Time::now() : h.stamp);
  return true;
}

void NodeAssimilation::queue(const Sample& s, const char* topic) {
  Rule rule = kRules;
  std::string why;
  // Ahead of the node's clock is the future (a sensor's clock off); ahead of the simulation
  // only, when it runs behind, the sample waits for it.
  const double clock = sim_seconds_(ros::Time::now());
  {
    std::lock_guard<PiMutex> lk(mutex_);
    if (s.t <= committed_) {
      rule = Stale;
      why = "stamped at t = " + std::to_string(s.t) + " s, at or before the estimate's window closed (t = " +
            std::to_string(committed_) + " s; ~assimilation/max_latency " + std::to_string(p_.max_latency) + " s)";
    } else if (s.t > std::max(clock, sim_time_) + p_.max_future) {
      rule = Future;
      why = "stamped at t = " + std::to_string(s.t) + " s, more than ~assimilation/max_future = " +
            std::to_string(p_.max_future) + " s ahead of the node's clock (t = " + std::to_string(clock) + " s)";
    } else {
      pending_.push_back(s);
    }
  }
  if (rule != kRules) refuse(rule, topic, why);
}

void NodeAssimilation::onWrench(const geometry_msgs::WrenchStamped::ConstPtr& m) {
  static const char* topic = "<needle>/measured_wrench";
  const Vec3 f = fromVector(m->wrench.force);
  if (!f.allFinite()) return refuse(NonFinite, topic, "a non-finite force");
  Sample s;
  Rigid r;
  if (!admit(m->header, topic, s.t, r)) return;
  if (m->header.frame_id == base_frame_) {
    s.force = f.x();  // the base frame's x: the axial force (as ~<needle>/wrench gives it)
  } else {
    std::lock_guard<PiMutex> lk(mutex_);
    s.force = (r.rotation * f).dot(axis_);  // along the needle, towards its tip
  }
  s.channel = 0;
  queue(s, topic);
}

void NodeAssimilation::onPoint(int channel, const char* topic, const geometry_msgs::PointStamped::ConstPtr& m) {
  const Vec3 q = fromPoint(m->point);
  if (!q.allFinite()) return refuse(NonFinite, topic, "a non-finite position");
  Sample s;
  Rigid r;
  if (!admit(m->header, topic, s.t, r)) return;
  if (m->header.frame_id == base_frame_) return refuse(Frame, topic, "a position in the moving base frame: give it in a fixed frame");
  s.channel = channel;
  s.point = r.apply(q);
  queue(s, topic);
}

void NodeAssimilation::onShape(const geometry_msgs::PoseArray::ConstPtr& m) {
  static const char* topic = "<needle>/measured_shape";
  const size_t n = m->poses.size();
  if (n == 0) return refuse(Shape, topic, "no pose: a shape needs at least its tip");
  // Points further back than the needle is long are not on it (a spacing or a length wrong).
  if (static_cast<double>(n - 1) * p_.shape_spacing > needle_length_ * (1 + 1e-9))
    return refuse(Shape, topic, std::to_string(n) + " poses at ~assimilation/shape_spacing " + std::to_string(p_.shape_spacing) +
                                    " m reach further back than the needle's " + std::to_string(needle_length_) + " m");
  for (const auto& q : m->poses)
    if (!fromPoint(q.position).allFinite()) return refuse(NonFinite, topic, "a non-finite position");
  Sample s;
  Rigid r;
  if (!admit(m->header, topic, s.t, r)) return;
  if (m->header.frame_id == base_frame_) return refuse(Frame, topic, "a shape in the moving base frame: give it in a fixed frame");
  s.channel = 3;
  // The message's last pose is the tip: the record's points run from the tip back.
  for (size_t i = n; i-- > 0;) s.shape.push_back(r.apply(fromPoint(m->poses[i].position)));
  queue(s, topic);
}

void NodeAssimilation::afterStep(Simulation& sim, const Observables& obs) {
  bool due = false;
  {
    std::lock_guard<PiMutex> lk(mutex_);
    if (adoption_) {
      // The stepping thread, between steps: the value the ramp has reached is what the next
      // step uses.
      if (adopt_clear_) adoption_ = std::make_unique<ParameterAdoption>(p_.keys, p_.adopt_ramp);
      adopt_clear_ = false;
      try {
        if (adopt_new_) {
          adoption_->target(sim, to_adopt_);
          ++adopted_;
        }
        adopt_new_ = false;
        if (adoption_->ramping()) adoption_->apply(sim);
      } catch (const InputError& e) {  // a value out of the key's range: the fit's bounds should prevent it
        adoption_ = std::make_unique<ParameterAdoption>(p_.keys, p_.adopt_ramp);
        adopt_failure_ = e.what();
        ROS_ERROR_THROTTLE(10.0, "needle_sim: assimilation: the estimate was not adopted: %s", e.what());
      }
      for (size_t i = 0; i < p_.keys.size(); ++i) in_use_[i] = sim.valueInUse(p_.keys[i]);
    }
    if (replay_)
      for (int i = 0; i < static_cast<int>(obs.needles.size()); ++i) {
        // The pose the base took in this step, as a command received at the step's start and
        // stamped at its end (reached then: the replay has no latency).
        RecordedCommand c;
        c.needle = i;
        c.received = sim_time_;
        c.command.stamp = sim.time();
        c.command.position = obs.needles[i].base;
        c.command.orientation = obs.needles[i].base_frame;
        commands_.push_back(c);
      }
    sim_time_ = sim.time();
    axis_ = obs.needles[needle_].base_frame * Vec3::UnitX();
    due = sim_time_ - p_.max_latency + 1e-12 >= next_due_;
  }
  if (due) wake_.notify_one();
}

void NodeAssimilation::setTarget(const std::string& name, const Vec3& planned) {
  std::lock_guard<PiMutex> lk(mutex_);
  target_edits_.push_back({name, planned});
  if (std::find(target_names_.begin(), target_names_.end(), name) == target_names_.end()) target_names_.push_back(name);
}

void NodeAssimilation::restart() {
  {
    std::lock_guard<PiMutex> lk(mutex_);
    ++generation_;
    cancel_ = true;  // the refit under way is of the old session
    pending_.clear();
    commands_.clear();
    target_edits_.clear();  // the new session's simulation has the scene's targets
    target_names_ = scene_target_names_;
    adopt_new_ = false;
    adopt_clear_ = true;  // the new session starts from the scene's values
    predictions_.clear();
    committed_ = -std::numeric_limits<double>::infinity();
    sim_time_ = 0;
    next_due_ = p_.every;
    // The session's estimate, for diagnostics: none yet.
    estimates_ = failures_ = 0;
    last_failure_.clear();
    consistent_ = true;
    last_t_ = -1, last_wall_ = last_rms_ = last_innovation_ = 0;
    last_values_.clear();
    last_stds_.clear();
  }
  wake_.notify_one();
  // The latched ~estimate is the old session's: replaced by one that has no samples yet (the
  // values NaN, the deviations infinite), so that a late subscriber is not told it.
  needle_sim::ParameterEstimate m;
  m.header.stamp = ros::Time::now();  // the reset
  m.header.frame_id = tissue_frame_;
  m.keys = p_.keys;
  m.values.assign(p_.keys.size(), kNaN);
  m.std.assign(p_.keys.size(), std::numeric_limits<double>::infinity());
  m.units = units_;
  m.innovation_force = m.innovation_tip = m.innovation_target = m.innovation_shape = kNaN;
  m.consistent = true;
  estimate_pub_.publish(m);
}

ForceRecord NodeAssimilation::rows(std::vector<Sample> batch) const {
  return measurementRows(std::move(batch), channels_[1], channels_[2] ? target_ : -1, num_targets_, channels_[3],
                         p_.shape_spacing);
}

void NodeAssimilation::worker() {
  nameThisThread("ns_assimilate");
  idleThisThread();  // work the live loop does not wait for (SCHED_IDLE)
  flushDenormalsToZero();
  std::unique_ptr<ForceAssimilation> a;
  ForceRecord held;  // rows taken before the estimator could start (it needs two)
  long generation = 0;
  // The session's base poses so far: those recorded since the last estimate are copied under
  // the lock (the stepping thread waits on it), the rest is kept here.
  std::vector<RecordedCommand> commands;
  std::vector<TargetEdit> target_edits;
  size_t taken = 0;
  for (;;) {
    std::vector<Sample> batch;
    double until = 0;
    long rejected = 0;
    {
      std::unique_lock<PiMutex> lk(mutex_);
      wake_.wait(lk, [&] { return stop_ || generation_ != generation || sim_time_ - p_.max_latency + 1e-12 >= next_due_; });
      if (stop_) return;
      if (generation_ != generation) {  // ~reset: a new session
        a.reset();
        held = ForceRecord{};
        commands.clear();
        target_edits.clear();
        taken = 0;
        generation = generation_;
        cancel_ = false;
        continue;
      }
      until = sim_time_ - p_.max_latency;
      next_due_ = until + p_.every;
      committed_ = until;
      auto later = std::stable_partition(pending_.begin(), pending_.end(), [&](const Sample& s) { return s.t <= until; });
      batch.assign(pending_.begin(), later);
      pending_.erase(pending_.begin(), later);
      if (replay_) {
        commands.insert(commands.end(), commands_.begin() + static_cast<std::ptrdiff_t>(taken), commands_.end());
        taken = commands_.size();
      }
      for (long n : refused_) rejected += n;
      target_edits = target_edits_;
    }
    if (batch.empty()) continue;
    ForceRecord r = rows(std::move(batch));
    try {
      if (!a) {
        if (held.t.empty()) {
          held = std::move(r);
        } else {
          held.t.insert(held.t.end(), r.t.begin(), r.t.end());
          held.force.insert(held.force.end(), r.force.begin(), r.force.end());
          held.tip.insert(held.tip.end(), r.tip.begin(), r.tip.end());
          held.shape.insert(held.shape.end(), r.shape.begin(), r.shape.end());
          for (size_t j = 0; j < held.targets.size(); ++j)
            held.targets[j].insert(held.targets[j].end(), r.targets[j].begin(), r.targets[j].end());
        }
        if (held.t.size() < 2) continue;
        AssimilationSettings s = settings_;
        s.fit.commands = commands;
        s.fit.target_edits = target_edits;
        // Adopted as soon as fitted, before the targets' prediction (whole-scene runs: seconds).
        s.on_fit = [this, &generation](const AssimilationCheckpoint& k) {
          std::lock_guard<PiMutex> lk(mutex_);
          if (generation_ != generation || cancel_ || !p_.adopt || !k.consistent) return;
          // A key the data do not determine yet (infinite std) keeps its value in use.
          to_adopt_ = k.values;
          for (size_t i = 0; i < to_adopt_.size(); ++i)
            if (!(i < k.stds.size() && std::isfinite(k.stds[i]))) to_adopt_[i] = kNaN;
          adopt_new_ = true;
        };
        a = std::make_unique<ForceAssimilation>(s, held);
        held = ForceRecord{};
      } else {
        a->append(r);
        if (replay_) a->setCommands(commands);
        a->setTargetEdits(target_edits);
      }
      const size_t before = a->checkpoints().size();
      a->update(until);
      std::lock_guard<PiMutex> lk(mutex_);
      if (generation_ != generation || cancel_) continue;  // reset meanwhile: the estimate is of the old session
      if (a->checkpoints().size() > before) {
        const AssimilationCheckpoint& k = a->checkpoints().back();
        ++estimates_;
        consistent_ = k.consistent;
        last_t_ = k.t;
        last_wall_ = k.wall_s;
        last_rms_ = k.rms;
        last_innovation_ = k.innovation_rms;
        last_values_ = k.values;
        last_stds_ = k.stds;
        outliers_ = a->outliers();
        predictions_.clear();
        for (size_t j = 0; j < k.target_end.size() && j < k.target_cov.size(); ++j)
          predictions_.push_back({k.t, k.target_end[j], k.target_cov[j]});
        publish(k, *a, rejected);
      }
    } catch (const std::exception& e) {
      // A fit that fails (the simulation diverges at a trial value, a record it cannot fit)
      // is reported, never published; the samples stay for the next attempt.
      std::lock_guard<PiMutex> lk(mutex_);
      if (cancel_) continue;  // stopped (the node's end, ~reset): the top of the loop starts anew
      ++failures_;
      last_failure_ = e.what();
      ROS_ERROR_THROTTLE(10.0, "needle_sim: assimilation: the estimate failed at t = %.3f s: %s", until, e.what());
    }
  }
}

std::vector<TargetPrediction> NodeAssimilation::predictions() {
  std::lock_guard<PiMutex> lk(mutex_);
  return predictions_;
}

void NodeAssimilation::publish(const AssimilationCheckpoint& k, const ForceAssimilation& a, long rejected) {
  needle_sim::ParameterEstimate m;
  m.header.stamp = ros_time_(k.t);
  m.header.frame_id = tissue_frame_;
  m.t = k.t;
  for (const auto& p : a.parameters()) m.keys.push_back(p.key);
  m.values = k.values;
  m.std = k.stds;
  m.samples = k.samples;
  m.new_samples = k.new_samples;
  m.outliers = a.outliers();
  m.rejected = rejected;
  m.rms_residual = k.rms;
  m.innovation_rms = k.innovation_rms;
  m.innovation_force = k.innovation_force;
  m.innovation_tip = k.innovation_tip;
  m.innovation_target = k.innovation_target;
  m.innovation_shape = k.innovation_shape;
  m.units = a.weights().units ? a.weights().units : units_;
  m.consistent = k.consistent;
  m.wall_s = k.wall_s;
  for (size_t j = 0; j < k.target_end.size() && j < target_names_.size(); ++j) {
    m.targets.push_back(target_names_[j]);
    m.target_positions.push_back(toPoint(k.target_end[j]));
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) m.target_covariances.push_back(j < k.target_cov.size() ? k.target_cov[j](r, c) : kNaN);
  }
  estimate_pub_.publish(m);
}

void NodeAssimilation::diagnose(diagnostic_updater::DiagnosticStatusWrapper& stat) {
  std::lock_guard<PiMutex> lk(mutex_);
  long rejected = 0;
  for (int r = 0; r < kRules; ++r) {
    stat.add(std::string("refused_") + kRuleNames[r], refused_[r]);
    rejected += refused_[r];
  }
  stat.add("estimates", estimates_);
  stat.add("failures", failures_);
  stat.add("outliers", outliers_);
  stat.add("adopted", p_.adopt ? std::to_string(adopted_) : std::string("off"));
  if (!adopt_failure_.empty()) stat.add("adopt_failure", adopt_failure_);
  stat.add("pending_samples", pending_.size());
  stat.addf("estimate_t", "%.9g", last_t_);
  stat.addf("estimate_wall_s", "%.6g", last_wall_);
  stat.addf("rms_residual", "%.9g", last_rms_);
  stat.addf("innovation_rms", "%.9g", last_innovation_);
  std::string values;
  for (size_t i = 0; i < p_.keys.size(); ++i) {
    const bool have = i < last_values_.size();
    stat.addf(p_.keys[i], "%.9g", have ? last_values_[i] : kNaN);
    stat.addf(p_.keys[i] + "_std", "%.9g", have && i < last_stds_.size() ? last_stds_[i] : kNaN);
    if (p_.adopt) stat.addf(p_.keys[i] + "_in_use", "%.9g", in_use_[i]);
    if (have) {
      char b[160];
      std::snprintf(b, sizeof b, "%s%s = %.4g +- %.2g", values.empty() ? "" : ", ", p_.keys[i].c_str(), last_values_[i],
                    i < last_stds_.size() ? last_stds_[i] : kNaN);
      values += b;
    }
  }
  if (!last_failure_.empty() && failures_ > 0 && estimates_ == 0)
    stat.summary(diagnostic_msgs::DiagnosticStatus::ERROR, "no estimate: " + last_failure_);
  else if (estimates_ == 0)
    stat.summary(diagnostic_msgs::DiagnosticStatus::OK, "waiting for measurements (" + std::to_string(rejected) + " refused)");
  else if (!consistent_)
    stat.summary(diagnostic_msgs::DiagnosticStatus::WARN,
                 "the model does not fit the measurements: residual RMS above 1.5 times the stated noise at t = " +
                     std::to_string(last_t_) + " s (" + values + "); the estimate is not to be trusted" +
                     (p_.adopt ? " (not adopted)" : ""));
  else
    stat.summary(diagnostic_msgs::DiagnosticStatus::OK, "estimate at t = " + std::to_string(last_t_) + " s: " + values +
                                                            (p_.adopt ? " (adopted)" : ""));
}

}  // namespace needle_sim

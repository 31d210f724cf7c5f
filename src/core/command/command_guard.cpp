#include "needle_sim/command/command_guard.hpp"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <cstdio>

#include "needle_sim/command/pose_convention.hpp"
#include "needle_sim/core/error.hpp"
#include "needle_sim/needle/duty_cycled_spin.hpp"

namespace needle_sim {

namespace {

struct RuleInfo {
  const char* name;
  const char* parameter;
  bool rejects;
};
constexpr RuleInfo kRules[kGuardRules] = {
    {"non_finite", "", true},
    {"quaternion_norm", "quaternion_tolerance", true},
    {"stale", "command_timeout", true},
    {"future", "max_future", true},
    {"out_of_order", "", true},
    {"workspace", "workspace_margin", true},
    {"frame", "tissue_frame", true},
    {"empty_frame", "allow_empty_frame", true},
    {"owner", "owner_timeout", true},
    {"plan", "", true},
    {"linear_speed", "max_speed", false},
    {"angular_speed", "max_angular_speed", false},
    {"angular_speed_inserted", "max_angular_speed_inserted", false},
};

std::string fmt(const char* f, double a, double b = 0, double c = 0) {
  char buf[200];
  std::snprintf(buf, sizeof buf, f, a, b, c);
  return buf;
}

// Samples of the interpolated path per segment: the rotation rate is taken as the largest
// over these sub-intervals (the interpolation is smooth: 32 samples are within 0.1 % of the
// true peak for turns up to 180 degrees; the tests check the sampled trajectory).
constexpr int kSamples = 32;

}  // namespace

const char* ruleName(GuardRule r) { return kRules[static_cast<int>(r)].name; }
const char* ruleParameter(GuardRule r) { return kRules[static_cast<int>(r)].parameter; }
bool ruleRejects(GuardRule r) { return kRules[static_cast<int>(r)].rejects; }

void CommandLimits::validate(const std::string& prefix) const {
  auto positive = [&](double v, const char* name) {
    if (!(v > 0) || !std::isfinite(v)) throw InputError("", prefix + name, "must be positive and finite");
  };
  auto non_negative = [&](double v, const char* name) {
    if (!(v >= 0) || !std::isfinite(v)) throw InputError("", prefix + name, "must be >= 0 and finite");
  };
  positive(max_speed, "max_speed");
  positive(max_angular_speed, "max_angular_speed");
  positive(max_angular_speed_inserted, "max_angular_speed_inserted");
  non_negative(max_future, "max_future");
  positive(command_timeout, "command_timeout");
  non_negative(workspace_margin, "workspace_margin");
  non_negative(command_latency, "command_latency");
  if (!(quaternion_tolerance > 0) || !(quaternion_tolerance < 1))
    throw InputError("", prefix + "quaternion_tolerance", "must be in (0, 1)");
  positive(owner_timeout, "owner_timeout");
  if (max_angular_speed_inserted > max_angular_speed)
    throw InputError("", prefix + "max_angular_speed_inserted", "must not exceed " + prefix + "max_angular_speed");
}

void LimitCeilings::validate(const std::string& prefix) const {
  for (const CeiledLimit& c : kCeiledLimits)
    if (!(this->*c.ceiling > 0) || !std::isfinite(this->*c.ceiling))
      throw InputError("", prefix + c.name + "_ceiling", "must be positive and finite");
}

void LimitCeilings::check(const CommandLimits& l, const std::string& prefix) const {
  for (const CeiledLimit& c : kCeiledLimits)
    if (l.*c.limit > this->*c.ceiling) {
      char buf[300];
      std::snprintf(buf, sizeof buf, "%.6g %s is above its ceiling %s%s_ceiling = %g %s (a start-up parameter)",
                    l.*c.limit, c.unit, prefix.c_str(), c.name, this->*c.ceiling, c.unit);
      throw InputError("", prefix + c.name, buf);
    }
}

SegmentMotion segmentMotion(const BaseTrajectory& traj, const BasePose& a, const BasePose& b,
                            const std::function<bool(const BasePose&)>& inside) {
  SegmentMotion m;
  m.distance = (b.position - a.position).norm();
  BasePose prev = a;
  Eigen::Quaterniond q_prev = traj.orientation(a);
  bool prev_in = inside && inside(a);
  for (int i = 1; i <= kSamples; ++i) {
    const BasePose p = traj.interpolate(a, b, static_cast<double>(i) / kSamples);
    const Eigen::Quaterniond q = traj.orientation(p);
    m.rotation = std::max(m.rotation, kSamples * q.angularDistance(q_prev));
    const double c = std::clamp(p.direction.dot(prev.direction), -1.0, 1.0);
    const double turn = kSamples * std::acos(c);
    m.axis_turn = std::max(m.axis_turn, turn);
    const bool in = inside && inside(p);
    if (in || prev_in) m.axis_turn_inside = std::max(m.axis_turn_inside, turn);
    prev = p;
    q_prev = q;
    prev_in = in;
  }
  return m;
}

CommandGuard::CommandGuard(const CommandLimits& limits, std::vector<NeedleInfo> needles, const LimitCeilings& ceilings,
                           std::string prefix)
    : prefix_(std::move(prefix)), limits_(limits), needles_(std::move(needles)), ceilings_(ceilings) {
  ceilings_.validate(prefix_);
  limits_.validate(prefix_);
  ceilings_.check(limits_, prefix_);
  for (auto& c : counts_) c = 0;
  restart();
}

void CommandGuard::setLimits(const CommandLimits& limits) {
  limits.validate(prefix_);
  ceilings_.check(limits, prefix_);
  std::lock_guard<PiMutex> lk(mutex_);
  limits_ = limits;
  ++limits_version_;
}

CommandLimits CommandGuard::limits() const {
  std::lock_guard<PiMutex> lk(mutex_);
  return limits_;
}

void CommandGuard::restart() {
  std::lock_guard<PiMutex> lk(mutex_);
  last_stamp_.assign(needles_.size(), -std::numeric_limits<double>::infinity());
  last_roll_.clear();
  for (const auto& n : needles_) last_roll_.push_back(n.rest.roll);
  taken_.assign(needles_.size(), Taken{});
  owners_.assign(needles_.size(), OwnerState{});
}

std::array<uint64_t, kGuardRules> CommandGuard::counts() const {
  std::array<uint64_t, kGuardRules> a{};
  for (int i = 0; i < kGuardRules; ++i) a[i] = counts_[i].load();
  return a;
}

uint64_t CommandGuard::rejected() const {
  uint64_t s = 0;
  for (int i = 0; i < kGuardRules; ++i)
    if (kRules[i].rejects) s += counts_[i].load();
  return s;
}

uint64_t CommandGuard::limited() const {
  uint64_t s = 0;
  for (int i = 0; i < kGuardRules; ++i)
    if (!kRules[i].rejects) s += counts_[i].load();
  return s;
}

std::string CommandGuard::named(const std::string& text) const {
  // "~<limit>" in the guard's own wording: the limit as its consumer names it. (Only the
  // limits' names: a sender's name such as "~insert" stays as it is.)
  static const char* const kLimitNames[] = {"max_speed", "max_angular_speed", "max_future", "command_timeout",
                                            "quaternion_tolerance", "workspace_margin", "command_latency",
                                            "owner_timeout"};
  std::string s;
  for (size_t i = 0; i < text.size(); ++i) {
    bool limit = false;
    if (text[i] == '~')
      for (const char* name : kLimitNames) limit = limit || text.compare(i + 1, std::strlen(name), name) == 0;
    s += limit ? prefix_ : std::string(1, text[i]);
  }
  return s;
}

Admission CommandGuard::reject(GuardRule r, const std::string& why) {
  record(r);
  Admission a;
  a.accepted = false;
  a.rule = r;
  a.reason = named(why);
  return a;
}

bool CommandGuard::checkPose(int n, const Vec3& p, const Eigen::Quaterniond& q, double roll_near, GuardRule& rule,
                             std::string& why, BasePose& pose) const {
  if (!p.allFinite() || !q.coeffs().allFinite()) {
    rule = GuardRule::NonFinite;
    why = "non-finite position or orientation";
    return false;
  }
  const double norm = q.norm();
  if (std::abs(norm - 1) > limits_.quaternion_tolerance) {
    rule = GuardRule::Quaternion;
    why = fmt("quaternion norm %.6g is not 1 (tolerance ~quaternion_tolerance = %g): not normalised, rejected", norm,
              limits_.quaternion_tolerance);
    return false;
  }
  const Vec3 lo = limits_.workspace_min - Vec3::Constant(limits_.workspace_margin);
  const Vec3 hi = limits_.workspace_max + Vec3::Constant(limits_.workspace_margin);
  if (((p - lo).array() < 0).any() || ((p - hi).array() > 0).any()) {
    rule = GuardRule::Workspace;
    why = fmt("position (%.4g, %.4g, %.4g) m is outside the workspace (the tissue's box plus ~workspace_margin)", p.x(),
              p.y(), p.z());
    return false;
  }
  pose = basePoseFrom(p, q.normalized(), needles_[n].rest, roll_near);
  return true;
}

bool CommandGuard::ownerAllows(int n, const std::string& source, double now, std::string& why) const {
  const OwnerState& o = owners_[n];
  if (o.source.empty() || o.source == source) return true;
  if (o.held) {
    why = "the needle is held by " + o.source + " (until it ends); commands from " + source + " are rejected";
    return false;
  }
  // The end of a plan it sent counts as its last command.
  const double silent = now - std::max(o.last, o.until);
  if (silent > limits_.owner_timeout) return true;  // given up: silent too long
  char buf[200];
  if (silent < 0)
    std::snprintf(buf, sizeof buf, "(its plan runs %.4g s more, and it keeps the needle ~owner_timeout = %g s after)",
                  -silent, limits_.owner_timeout);
  else
    std::snprintf(buf, sizeof buf, "(until it has been silent for ~owner_timeout = %g s; its last command %.4g s ago)",
                  limits_.owner_timeout, silent);
  why = named("the needle is commanded by " + o.source + " " + buf + "; commands from " + source + " are rejected");
  return false;
}

bool CommandGuard::mayCommand(int n, const std::string& source, double now, std::string& why) {
  std::lock_guard<PiMutex> lk(mutex_);
  if (ownerAllows(n, source, now, why)) return true;
  record(GuardRule::Owner);
  return false;
}

void CommandGuard::own(int n, const std::string& source, double now, double until) {
  std::lock_guard<PiMutex> lk(mutex_);
  OwnerState& o = owners_[n];
  if (o.source != source) o = OwnerState{source, now, until, false};
  o.last = std::max(o.last, now);
  o.until = std::max(o.until, until);
}

bool CommandGuard::hold(int n, const std::string& source, double now, std::string& why) {
  std::lock_guard<PiMutex> lk(mutex_);
  if (!ownerAllows(n, source, now, why)) {
    record(GuardRule::Owner);
    return false;
  }
  owners_[n] = OwnerState{source, now, now, true};
  return true;
}

void CommandGuard::release(int n, const std::string& source) {
  std::lock_guard<PiMutex> lk(mutex_);
  if (owners_[n].source == source) owners_[n] = OwnerState{};
}

std::string CommandGuard::owner(int n) const {
  std::lock_guard<PiMutex> lk(mutex_);
  return owners_[n].source;
}

Admission CommandGuard::admit(int n, const PoseCommand& c, double now) {
  std::lock_guard<PiMutex> lk(mutex_);
  // One source at a time: another's command is rejected before anything else is looked at;
  // the owner's own commands, taken or not, show it is not silent.
  if (!c.source.empty()) {
    std::string why;
    if (!ownerAllows(n, c.source, now, why)) return reject(GuardRule::Owner, why);
    if (owners_[n].source == c.source) owners_[n].last = std::max(owners_[n].last, now);
  }
  const bool stamped = !std::isnan(c.stamp);
  if (stamped && !std::isfinite(c.stamp)) return reject(GuardRule::NonFinite, "non-finite stamp");
  const double stamp = stamped ? c.stamp : now;
  if (now - stamp > limits_.command_timeout)
    return reject(GuardRule::Stale,
                  fmt("stale: stamped %.4g s ago (~command_timeout = %g s)", now - stamp, limits_.command_timeout));
  if (stamp - now > limits_.max_future)
    return reject(GuardRule::Future, fmt("stamped %.4g s in the future (~max_future = %g s): clocks out of sync?",
                                         stamp - now, limits_.max_future));
  if (stamp < last_stamp_[n])
    return reject(GuardRule::OutOfOrder, fmt("stamped %.4g s before the last accepted command: out of order",
                                             last_stamp_[n] - stamp));
  Admission a;
  GuardRule rule;
  std::string why;
  if (!checkPose(n, c.position, c.orientation, last_roll_[n], rule, why, a.pose)) return reject(rule, why);
  a.accepted = true;
  a.at = stamp + limits_.command_latency;
  last_stamp_[n] = stamp;
  last_roll_[n] = a.pose.roll;
  if (!c.source.empty() && owners_[n].source != c.source) owners_[n] = OwnerState{c.source, now, now, false};
  return a;
}

bool CommandGuard::tipInTissue(int n, const BasePose& p, const CommandLimits& l) const {
  const Vec3 tip = p.position + needles_[n].length * p.direction;
  return ((tip - l.workspace_min).array() >= 0).all() && ((tip - l.workspace_max).array() <= 0).all();
}

double CommandGuard::needed(int n, const BaseTrajectory& traj, const BasePose& from, const BasePose& to,
                            bool inserted, const CommandLimits& l, GuardRule& rule) const {
  const SegmentMotion m =
      segmentMotion(traj, from, to, [&](const BasePose& p) { return inserted || tipInTissue(n, p, l); });
  double need = m.distance / l.max_speed;
  rule = GuardRule::LinearSpeed;
  if (m.rotation / l.max_angular_speed > need) {
    need = m.rotation / l.max_angular_speed;
    rule = GuardRule::AngularSpeed;
  }
  if (m.axis_turn_inside / l.max_angular_speed_inserted > need) {
    need = m.axis_turn_inside / l.max_angular_speed_inserted;
    rule = GuardRule::AngularInserted;
  }
  return need;
}

Following CommandGuard::follow(int n, BaseTrajectory& traj, const Admission& a, double now, double dt, bool inserted) {
  const CommandLimits lim = limits();
  // The command asks to be reached at a.at, never within the step under way. The base leaves
  // what was commanded before at the later of now and the last keyframe before that time:
  // a keyframe the base has not reached yet and that this command supersedes (one slowed
  // down by a limit, or one for the same instant) is dropped, one that was reached stays.
  const double te = std::max(a.at, now + dt);
  const double ts = std::max(now, traj.lastKeyTimeBefore(te));
  traj.holdFrom(ts);
  const BasePose from = traj.pose(ts);
  Taken taken;
  {
    std::lock_guard<PiMutex> lk(mutex_);
    Taken& k = taken_[n];
    if (!(k.step_now == now)) {
      k.before = k.last;
      k.first = a.at;
      k.step_now = now;
    }
    k.last = a.at;
    taken = k;
  }
  Following f;
  const double need = needed(n, traj, from, a.pose, inserted, lim, f.rule);
  double t = te;
  if (ts + need > te) {
    // Too fast for a limit: reached later, at the limit's pace. Counted when it is more than
    // a step late (a stream's jitter of arrival makes single steps a little short). Commands
    // that arrive after their time (the node lagged, a tf sample was skipped, a batch came in
    // one step) are given the lag of the first of them, up to the time their stream gave
    // the motion since the last command taken at an earlier step: that lag is the node's,
    // reported as lag, not a command too fast.
    const double late = std::max(0.0, now + dt - taken.first);
    const double fair_end = te + std::min(late, std::max(0.0, a.at - taken.before));
    if (ts + need > fair_end + dt) {
      f.limited = true;
      record(f.rule);
    }
    t = ts + need;
  }
  if (t > ts) traj.add(t, a.pose);
  // (t == ts: the pose is where the base is at ts, nothing to move)
  if (traj.size() > 256) traj.dropBefore(now);
  f.reached_at = t;
  return f;
}

bool CommandGuard::enforce(int n, BaseTrajectory& traj, double now, bool inserted) {
  const CommandLimits lim = limits();
  const auto keys = traj.keyframesAfter(now);
  if (keys.empty()) return false;
  // Re-timed from now: each segment takes at least what the limits need; the poses stay.
  traj.holdFrom(now);
  BasePose prev = traj.pose(now);
  double t_prev = now, shift = 0;
  for (const auto& [t, pose] : keys) {
    GuardRule rule;
    const double need = needed(n, traj, prev, pose, inserted, lim, rule);
    const double t_new = std::max(t + shift, t_prev + need);
    shift = t_new - t;
    if (t_new > t_prev) traj.add(t_new, pose);
    prev = pose;
    t_prev = std::max(t_prev, t_new);
  }
  return shift > 1e-12;
}

std::string CommandGuard::checkPlan(int n, const std::vector<PlanWaypoint>& w, const BasePose& from, double dt,
                                    bool inserted, PlanPoses& out) {
  std::lock_guard<PiMutex> lk(mutex_);
  out.clear();
  auto refuse = [&](size_t k, const std::string& why) {
    record(GuardRule::Plan);
    out.clear();
    return "waypoint " + std::to_string(k) + ": " + named(why);
  };
  if (w.empty()) {
    record(GuardRule::Plan);
    return "no waypoints";
  }
  // Rates are measured with the trajectory's own interpolation (rest pose of this needle).
  const BaseTrajectory shape(needles_[n].rest);
  auto inside = [&](const BasePose& p) { return inserted || tipInTissue(n, p, limits_); };
  BasePose prev = from;
  double t_prev = 0;
  for (size_t k = 0; k < w.size(); ++k) {
    const double t = w[k].time;
    if (!std::isfinite(t) || t < 0 || (k > 0 && t <= t_prev)) return refuse(k, "time_from_start not increasing");
    if (k > 0 && t < dt)
      return refuse(k, fmt("time_from_start %.4g s: within the plan's first step (%g s); only the first waypoint "
                           "may be", t, dt));
    GuardRule rule;
    std::string why;
    BasePose p;
    if (!checkPose(n, w[k].position, w[k].orientation, prev.roll, rule, why, p))
      return refuse(k, std::string(ruleName(rule)) + ": " + why);
    // Each segment over its own duration: waypoints closer together than a step are not
    // given a step each (they would run faster than planned). The first segment, from where
    // the base is, gets at least a step (the plan starts at the next step boundary).
    const double span = k == 0 ? std::max(t, dt) : t - t_prev;
    const SegmentMotion m = segmentMotion(shape, prev, p, inside);
    const double tol = 1 + 1e-9;
    if (m.distance / span > limits_.max_speed * tol)
      return refuse(k, fmt("linear_speed: %.4g m/s, faster than ~max_speed = %g m/s", m.distance / span,
                           limits_.max_speed));
    if (m.rotation / span > limits_.max_angular_speed * tol)
      return refuse(k, fmt("angular_speed: %.4g rad/s, faster than ~max_angular_speed = %g rad/s", m.rotation / span,
                           limits_.max_angular_speed));
    if (m.axis_turn_inside / span > limits_.max_angular_speed_inserted * tol)
      return refuse(k, fmt("angular_speed_inserted: the axis turns at %.4g rad/s in the tissue, faster than "
                           "~max_angular_speed_inserted = %g rad/s",
                           m.axis_turn_inside / span, limits_.max_angular_speed_inserted));
    if (!std::isfinite(w[k].spin_rate) || w[k].spin_rate < 0 || !std::isfinite(w[k].spin_duty))
      return refuse(k, "spin_rate and spin_duty must be finite, spin_rate >= 0");
    if (w[k].spin_duty < 0 || w[k].spin_duty > 1)
      return refuse(k, fmt("spin_duty %.4g: must be in [0, 1] (the fraction of the segment spent spinning)",
                           w[k].spin_duty));
    if (w[k].spin_duty > 0) {
      if (!(w[k].spin_rate > 0)) return refuse(k, "spin_duty > 0 needs spin_rate > 0");
      if (k + 1 == w.size()) return refuse(k, "spin on the last waypoint: there is no segment after it to spin over");
      if (w[k].spin_rate > limits_.max_angular_speed * tol)
        return refuse(k, fmt("angular_speed: spin_rate %.4g rad/s, faster than ~max_angular_speed = %g rad/s",
                             w[k].spin_rate, limits_.max_angular_speed));
    }
    out.emplace_back(t, p);
    prev = p;
    t_prev = t;
  }
  return spinPlan(w, shape, refuse, out);
}

std::string CommandGuard::spinPlan(const std::vector<PlanWaypoint>& w, const BaseTrajectory& shape,
                                   const std::function<std::string(size_t, const std::string&)>& refuse,
                                   PlanPoses& out) const {
  bool any = false;
  for (const PlanWaypoint& x : w) any = any || x.spin_duty > 0;
  if (!any) return "";
  // The spinning segments become whole turns and holds (duty_cycled_spin.hpp); the turns are
  // as fast as spin_rate only up to the rounding to whole turns, so each is checked again.
  std::vector<NeedleMotionKey> keys;
  for (size_t k = 0; k < w.size(); ++k) {
    NeedleMotionKey key;
    key.t = out[k].first;
    key.position = out[k].second.position;
    key.direction = out[k].second.direction;
    key.roll = out[k].second.roll;
    key.spin_rate = w[k].spin_rate;
    key.spin_duty = w[k].spin_duty;
    keys.push_back(key);
  }
  const std::vector<NeedleMotionKey> turns = expandDutyCycledSpin(keys, shape.rest());
  PlanPoses expanded;
  size_t k = 0;  // the waypoint whose segment the piece ending at key i is in
  for (size_t i = 0; i < turns.size(); ++i) {
    const BasePose p{turns[i].position, turns[i].direction, turns[i].roll};
    if (i > 0) {
      while (k + 1 < w.size() && turns[i - 1].t >= out[k + 1].first) ++k;
      const double span = turns[i].t - expanded.back().first;
      const SegmentMotion m = segmentMotion(shape, expanded.back().second, p);
      if (!(span > 0) || m.rotation / span > limits_.max_angular_speed * (1 + 1e-9)) {
        out.clear();
        return refuse(k, fmt("angular_speed: the spin's whole turns run at %.4g rad/s, faster than "
                             "~max_angular_speed = %g rad/s (a longer segment or a lower duty)",
                             m.rotation / span, limits_.max_angular_speed));
      }
    }
    expanded.emplace_back(turns[i].t, p);
  }
  out = std::move(expanded);
  return "";
}

void CommandGuard::planTaken(int n, const BasePose& last) {
  std::lock_guard<PiMutex> lk(mutex_);
  last_roll_[n] = last.roll;
}

}  // namespace needle_sim

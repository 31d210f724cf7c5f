#include "needle_sim/sim/command_pipeline.hpp"

#include "needle_sim/sim/simulation.hpp"

namespace needle_sim {

namespace {
// The workspace the guard allows: the tissue's box, or the first needle's base without one.
CommandLimits withWorkspace(CommandLimits l, const Simulation& sim) {
  if (sim.hasTissue()) {
    l.workspace_min = sim.tissue().mesh().boundsMin();
    l.workspace_max = sim.tissue().mesh().boundsMax();
  } else {
    const Scene& s = sim.scene();
    l.workspace_min = l.workspace_max = s.needles.empty() ? Vec3::Zero() : s.needles[0].base_position;
  }
  return l;
}
}  // namespace

CommandPipeline::CommandPipeline(const Simulation& sim, const CommandLimits& limits, const LimitCeilings& ceilings,
                                 const std::string& prefix) {
  std::vector<CommandGuard::NeedleInfo> info;
  for (const auto& n : sim.scene().needles) info.push_back({{n.base_position, n.base_direction, n.base_roll}, n.length});
  guard_ = std::make_unique<CommandGuard>(withWorkspace(limits, sim), std::move(info), ceilings, prefix);
  limits_version_ = guard_->limitsVersion();
}

void CommandPipeline::restart(const Simulation& sim) {
  guard_->setLimits(withWorkspace(guard_->limits(), sim));
  guard_->restart();
  limits_version_ = guard_->limitsVersion();
  std::lock_guard<PiMutex> lk(mutex_);
  commands_.clear();
  plans_.clear();
  holds_.clear();
}

bool CommandPipeline::inserted(const Simulation& sim, int needle) {
  return sim.interaction() && sim.interaction()->activePoints(needle) > 0;
}

Admission CommandPipeline::submit(int needle, const PoseCommand& command, double now) {
  std::lock_guard<PiMutex> lk(mutex_);  // (admission and queueing in arrival order)
  const Admission a = guard_->admit(needle, command, now);
  if (a.accepted) commands_.emplace_back(needle, a);
  return a;
}

void CommandPipeline::submitPlan(Plan plan) {
  std::lock_guard<PiMutex> lk(mutex_);
  plans_.push_back(std::move(plan));
}

void CommandPipeline::hold(int needle) {
  std::lock_guard<PiMutex> lk(mutex_);
  holds_.push_back(needle);
}

std::string CommandPipeline::checkPlan(const Simulation& sim, int needle, const std::vector<PlanWaypoint>& w,
                                       PlanPoses& out) {
  const double now = sim.time();
  return guard_->checkPlan(needle, w, sim.needle(needle).trajectory().pose(now), sim.dt(), inserted(sim, needle), out);
}

std::vector<CommandPipeline::Event> CommandPipeline::beforeStep(Simulation& sim) {
  std::vector<std::pair<int, Admission>> cmds;
  std::vector<Plan> plans;
  std::vector<int> holds;
  {
    std::lock_guard<PiMutex> lk(mutex_);
    cmds.swap(commands_);
    plans.swap(plans_);
    holds.swap(holds_);
  }
  std::vector<Event> events;
  const double now = sim.time(), dt = sim.dt();
  for (int n : holds) sim.needle(n).trajectory().holdFrom(now);
  // New limits (dynamic_reconfigure) apply to what is under way too, not only to new commands.
  if (guard_->limitsVersion() != limits_version_ && enforce_on_motion_) {
    limits_version_ = guard_->limitsVersion();
    for (int n = 0; n < sim.numNeedles(); ++n)
      if (guard_->enforce(n, sim.needle(n).trajectory(), now, inserted(sim, n))) {
        Event e;
        e.kind = Event::Kind::Enforced;
        e.needle = n;
        events.push_back(e);
      }
  }
  for (size_t i = 0; i < cmds.size(); ++i) {
    const auto& [n, a] = cmds[i];
    // A later command of the same needle for the same instant supersedes this one.
    if (i + 1 < cmds.size() && cmds[i + 1].first == n && cmds[i + 1].second.at == a.at) continue;
    Event taken;
    taken.needle = n;
    taken.source = "a pose command";
    events.push_back(taken);
    const Following f = guard_->follow(n, sim.needle(n).trajectory(), a, now, dt, inserted(sim, n));
    if (f.limited) {
      Event e;
      e.kind = Event::Kind::Limited;
      e.needle = n;
      e.rule = f.rule;
      e.why = "reached " + std::to_string(f.reached_at - std::max(a.at, now + dt)) + " s later than asked";
      events.push_back(e);
    }
  }
  for (auto& p : plans) {
    BaseTrajectory& traj = sim.needle(p.needle).trajectory();
    PlanPoses poses;
    std::string why;
    Event e;
    e.needle = p.needle;
    e.source = p.source;
    // One source at a time: a plan from another than the needle's owner is refused whole.
    if (!p.owner.empty() && !guard_->mayCommand(p.needle, p.owner, now, why)) {
      e.kind = Event::Kind::Refused;
      e.rule = GuardRule::Owner;
      e.why = why;
      events.push_back(e);
      if (p.done) p.done("owner: " + why);
      continue;
    }
    why = guard_->checkPlan(p.needle, p.waypoints, traj.pose(now), dt, inserted(sim, p.needle), poses);
    if (!why.empty()) {
      e.kind = Event::Kind::Refused;
      e.rule = GuardRule::Plan;
      e.why = why;
    } else {
      if (!p.owner.empty()) guard_->own(p.needle, p.owner, now, now + dt + poses.back().first);
      traj.holdFrom(now);
      traj.replaceFrom(now, dt, poses);
      guard_->planTaken(p.needle, poses.back().second);
      e.kind = Event::Kind::Taken;
      e.plan = true;
      e.has_done = static_cast<bool>(p.done);
    }
    events.push_back(e);
    if (p.done) p.done(why);
  }
  return events;
}

}  // namespace needle_sim

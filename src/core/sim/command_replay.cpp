#include "needle_sim/sim/command_replay.hpp"

#include "needle_sim/sim/simulation.hpp"

namespace needle_sim {

CommandReplay::CommandReplay(const Simulation& sim, const CommandLimits& limits, std::vector<RecordedCommand> commands)
    : commands_(std::move(commands)) {
  CommandLimits l = limits;
  const Scene& scene = sim.scene();
  // As the node: the workspace is the tissue's box (plus the margin).
  if (sim.hasTissue()) {
    l.workspace_min = sim.tissue().mesh().boundsMin();
    l.workspace_max = sim.tissue().mesh().boundsMax();
  } else {
    l.workspace_min = l.workspace_max = scene.needles.empty() ? Vec3::Zero() : scene.needles[0].base_position;
  }
  std::vector<CommandGuard::NeedleInfo> info;
  for (const auto& n : scene.needles) info.push_back({{n.base_position, n.base_direction, n.base_roll}, n.length});
  guard_ = std::make_unique<CommandGuard>(l, std::move(info));
}

void CommandReplay::beforeStep(Simulation& sim) {
  const double now = sim.time(), dt = sim.dt();
  std::vector<std::pair<int, Admission>> admitted;
  // Received before the step starts (the node's stepping thread takes what arrived by then).
  while (next_ < commands_.size() && commands_[next_].received <= now + 1e-12) {
    const RecordedCommand& c = commands_[next_++];
    if (c.needle < 0 || c.needle >= sim.numNeedles()) continue;
    if (c.frame_rule == GuardRule::Frame || c.frame_rule == GuardRule::EmptyFrame) {
      guard_->record(c.frame_rule);
      continue;
    }
    const Admission a = guard_->admit(c.needle, c.command, c.received);
    if (a.accepted) admitted.emplace_back(c.needle, a);
  }
  for (size_t i = 0; i < admitted.size(); ++i) {
    const auto& [n, a] = admitted[i];
    // A later command of the same needle for the same instant supersedes this one.
    if (i + 1 < admitted.size() && admitted[i + 1].first == n && admitted[i + 1].second.at == a.at) continue;
    const bool inserted = sim.interaction() && sim.interaction()->activePoints(n) > 0;
    guard_->follow(n, sim.needle(n).trajectory(), a, now, dt, inserted);
    ++accepted_;
  }
}

}  // namespace needle_sim

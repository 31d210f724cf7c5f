#include "needle_sim/sim/command_replay.hpp"

#include "needle_sim/sim/simulation.hpp"

namespace needle_sim {

CommandReplay::CommandReplay(const Simulation& sim, const CommandLimits& limits, std::vector<RecordedCommand> commands)
    : pipeline_(sim, limits), commands_(std::move(commands)) {}

void CommandReplay::beforeStep(Simulation& sim) {
  const double now = sim.time();
  // Received before the step starts (the node's stepping thread takes what arrived by then).
  while (next_ < commands_.size() && commands_[next_].received <= now + 1e-12) {
    const RecordedCommand& c = commands_[next_++];
    if (c.needle < 0 || c.needle >= sim.numNeedles()) continue;
    if (c.frame_rule == GuardRule::Frame || c.frame_rule == GuardRule::EmptyFrame) {
      pipeline_.guard().record(c.frame_rule);
      continue;
    }
    pipeline_.submit(c.needle, c.command, c.received);
  }
  for (const CommandPipeline::Event& e : pipeline_.beforeStep(sim))
    if (e.kind == CommandPipeline::Event::Kind::Taken) ++accepted_;
}

}  // namespace needle_sim

#pragma once
// A recorded command stream applied to a simulation headless, the way the node applies it
// (doc/cli.md, "run --bag"): every pose command goes through the command pipeline
// (sim/command_pipeline.hpp) with the node's default limits, submitted at the time it was
// received and followed at the next step boundary, so a recorded session replays with the
// same rules (stamps, limits, workspace, one source per needle) as on the robot, as fast as
// the machine allows. No ROS here: the tool reads the bag.
#include <memory>
#include <vector>

#include "needle_sim/sim/command_pipeline.hpp"

namespace needle_sim {

class Simulation;

// One recorded command: the needle it drives, when it was received [s since the recording's
// start], the pose as sent (in the tissue frame) with its stamp in the same seconds;
// frame_rule: Frame or EmptyFrame when it was given in a frame the replay cannot transform
// (one the bag's tf does not resolve) or in none (counted under that rule, rejected, as by the
// node);
// NonFinite (the default) when its frame is the tissue frame.
struct RecordedCommand {
  int needle = 0;
  double received = 0;
  PoseCommand command;
  GuardRule frame_rule = GuardRule::NonFinite;
};

class CommandReplay {
 public:
  // commands in the order they were received.
  CommandReplay(const Simulation& sim, const CommandLimits& limits, std::vector<RecordedCommand> commands);
  // Before each sim.step(): submits the commands received up to the step's start and applies
  // them.
  void beforeStep(Simulation& sim);
  const CommandGuard& guard() const { return pipeline_.guard(); }
  long accepted() const { return accepted_; }
  long pending() const { return static_cast<long>(commands_.size() - next_); }

 private:
  CommandPipeline pipeline_;
  std::vector<RecordedCommand> commands_;
  size_t next_ = 0;
  long accepted_ = 0;
};

}  // namespace needle_sim

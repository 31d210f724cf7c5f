#pragma once
// The one way commands reach a simulation's needles (doc/ros_api.md, "Command guard"): the
// node's pose topic, tf, trajectory topics, action and services, the tool's bag replay,
// `needle_sim steer`'s live run and the predictions all go through it, so a needle moves by
// the same rules whoever drives it.
//   submit()      a pose command on arrival (any thread): the guard's checks (finite, unit
//                 quaternion, stamp, workspace, one source per needle); queued when accepted;
//   submitPlan()  a plan (any thread), checked whole at the next step boundary against the
//                 base's commanded pose then, and against the needle's owner;
//   hold()        the needle stops where it is, at the next step boundary;
//   beforeStep()  the stepping thread, at a step boundary: limits changed since are enforced
//                 on the motion under way, then holds, the queued commands (followed, slowed
//                 to the limits, never jumped to) and the plans (taken or refused whole);
//                 returns what happened, for the caller to report;
//   checkPlan()   a plan against the state of now without taking it (a prediction's).
// Whether a needle is in the tissue (the in-tissue turn limit) is asked here, in one place.
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "needle_sim/command/command_guard.hpp"
#include "needle_sim/core/pi_mutex.hpp"

namespace needle_sim {

class Simulation;

class CommandPipeline {
 public:
  struct Plan {
    int needle = 0;
    std::vector<PlanWaypoint> waypoints;  // time from the step it is taken at
    std::string source;                   // for messages ("~needle/command_trajectory", "~insert goal")
    // Called on the stepping thread: "" when taken, else why it was refused.
    std::function<void(const std::string&)> done;
    // Who sends it (rule owner: a caller id, a holder's name); "": not arbitrated. Taken, it
    // owns the needle until the plan's end at least.
    std::string owner;
  };
  // What beforeStep() did, for the caller to report (the node warns, the action learns it was
  // superseded).
  struct Event {
    enum class Kind {
      Taken,     // a pose command or a plan now drives the needle
      Limited,   // a pose command slowed down by a limit (rule, why)
      Refused,   // a plan refused whole (rule Plan or Owner, why)
      Enforced,  // the motion under way slowed down to limits changed since
    } kind = Kind::Taken;
    int needle = 0;
    GuardRule rule = GuardRule::Plan;
    std::string source, why;
    bool plan = false;      // Taken: a plan (else a pose command)
    bool has_done = false;  // Taken: a plan whose sender learns it itself (done callback)
  };

  // The guard's workspace is the tissue's box (or the first needle's base without tissue);
  // its needles are the scene's; prefix: how the consumer names the limits in messages ("~" for
  // the node's parameters). Throws InputError for limits out of range or above a ceiling.
  CommandPipeline(const Simulation& sim, const CommandLimits& limits, const LimitCeilings& ceilings = {},
                  const std::string& prefix = "");
  // A new simulation of the same scene (~reset): the limits as they are now, queues emptied,
  // the stamp order and the owners forgotten (the counters go on).
  void restart(const Simulation& sim);

  CommandGuard& guard() { return *guard_; }
  const CommandGuard& guard() const { return *guard_; }
  // Whether limits changed since are enforced on the motion under way (not on a scene's own
  // motion: the node with ~command_source scene).
  void enforceOnMotion(bool on) { enforce_on_motion_ = on; }
  // The needle is in the tissue (it has constraint points).
  static bool inserted(const Simulation& sim, int needle);

  // Any thread. now: the simulation time of arrival.
  Admission submit(int needle, const PoseCommand& command, double now);
  void submitPlan(Plan plan);
  void hold(int needle);
  // The stepping thread, before each step.
  std::vector<Event> beforeStep(Simulation& sim);
  // A plan from the needle's commanded pose now: "" and its base poses in `out`, or why not.
  std::string checkPlan(const Simulation& sim, int needle, const std::vector<PlanWaypoint>& waypoints,
                        PlanPoses& out);

 private:
  std::unique_ptr<CommandGuard> guard_;
  long limits_version_ = 0;  // of the limits the motion under way was last checked against
  bool enforce_on_motion_ = true;
  PiMutex mutex_;         // the queues
  std::vector<std::pair<int, Admission>> commands_;
  std::vector<Plan> plans_;
  std::vector<int> holds_;
};

}  // namespace needle_sim

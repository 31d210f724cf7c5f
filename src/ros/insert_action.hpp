#pragma once
// The ~insert action (needle_sim/InsertNeedle): a straight insertion along the needle's
// current axis, towards a named target or a point, by a depth or to a stop distance, at a
// speed; feedback (tip-target distance, holder force, insertion state) at 10 Hz of simulated
// time; preempted (cancel, or a new goal), the needle holds where it is. The motion is a
// plan the command guard checks like any other. Goal handles are only touched from the
// callback threads and the output thread, never under the simulation's lock (actionlib
// calls back with its own lock held). A goal holds its needle (command guard, rule owner):
// it is rejected while another source commands the needle, and while it runs, commands from
// any other source are rejected; it gives the needle back when it ends.
#include <actionlib/server/action_server.h>
#include <needle_sim/InsertNeedleAction.h>

#include <mutex>
#include <optional>
#include <string>

#include "needle_sim/core/types.hpp"
#include "needle_sim/sim/observables.hpp"
#include "needle_sim/core/pi_mutex.hpp"

namespace needle_sim {

class SimulatorRos;

class InsertAction {
 public:
  using Server = actionlib::ActionServer<needle_sim::InsertNeedleAction>;
  InsertAction(SimulatorRos& node, ros::NodeHandle& pnh, double default_speed);
  // On the stepping thread (the simulation's lock held), after each step.
  void update(const Observables& o);
  // Ends the goal under way (a numerical failure, a reset).
  void abort(const std::string& why);
  // Another command took over needle n (stepping thread): the goal on it is aborted.
  void superseded(int needle, const std::string& by);
  void shutdown();

 private:
  void onGoal(Server::GoalHandle gh);
  void onCancel(Server::GoalHandle gh);
  struct Active {
    Server::GoalHandle gh;
    int needle = 0;
    int target = -1;  // index, or -1: the fixed point
    Vec3 point = Vec3::Zero();
    Vec3 axis = Vec3::UnitX(), base0 = Vec3::Zero();
    double duration = 0;  // of the motion [s]
    double end = 0;       // simulation time it ends (known once the plan is taken)
    double last_feedback = -1;
    double max_tip_speed = 0;  // observed over the goal's steps
    bool taken = false;
  };
  // The goal holds its needle (rule owner) from acceptance until it ends, whatever ends it.
  static constexpr const char* kHolder = "~insert";
  void release(const Active& a);
  needle_sim::InsertNeedleResult result(const Active& a, const Observables& o, const std::string& msg) const;
  SimulatorRos& node_;
  double default_speed_;
  PiMutex mutex_;  // active_
  std::optional<Active> active_;
  Server server_;
};

}  // namespace needle_sim

#pragma once
// The command guard: the last check between a robot's commands and the simulated needle
// (doc/ros_api.md, "Command guard"). Every command path of the node (pose topic, tf,
// trajectory topics, predict, the insertion action) goes through it:
//   admit()      per pose command, on arrival: finite, unit quaternion, stamp neither stale,
//                nor too far ahead, nor older than the last accepted one, inside the
//                workspace; converted to (axis, roll) in the pose convention.
//   follow()     per admitted command, at a step boundary: the base leaves what it was
//                commanded before at the instant the new command takes over and approaches
//                the new pose no faster than the linear and angular limits (a command that
//                asks for more is slowed down, counted, never jumped to), also after a pause.
//   checkPlan()  a planned trajectory, whole: any waypoint breaking a rule or a limit
//                rejects it (a plan is never silently changed).
//   ownership    one source commands a needle at a time (rule owner): the first source
//                whose command is accepted owns the needle until it has been silent for
//                owner_timeout; an action or a service holds it explicitly (hold/release).
// Rules are counted one by one (lifetime counters, thread-safe), so a robot team sees which
// rule its commands break. No ROS here: times are simulation seconds.
#include <array>
#include <atomic>
#include <functional>
#include <cstdint>
#include <limits>
#include <mutex>
#include <string>
#include <utility>
#include <vector>

#include <Eigen/Geometry>

#include "needle_sim/core/types.hpp"
#include "needle_sim/needle/base_trajectory.hpp"
#include "needle_sim/core/pi_mutex.hpp"

namespace needle_sim {

// The limits, each a node parameter of the same name (doc/ros_api.md).
struct CommandLimits {
  double max_speed = 0.05;               // [m/s] base translation
  double max_angular_speed = 1.0;        // [rad/s] base rotation (axis turn and roll together)
  double max_angular_speed_inserted = 0.1;  // [rad/s] turn of the needle axis while it is in the tissue
  double max_future = 0.01;              // [s] stamps further ahead of now are rejected
  double command_timeout = 0.5;          // [s] stamps older than this are rejected
  double quaternion_tolerance = 0.01;    // | |q| - 1 | above this: rejected, not normalised
  double workspace_margin = 0.2;         // [m] around the tissue's box
  double command_latency = 0.005;        // [s] a stamped command is reached at stamp + this
  double owner_timeout = 0.5;            // [s] a needle's owner that is silent this long gives it up
  Vec3 workspace_min = Vec3::Zero(), workspace_max = Vec3::Zero();  // the tissue's box
  // Throws InputError (key: prefix + parameter name) for a limit out of its range.
  void validate(const std::string& prefix = "") const;
};

// Hard ceilings of the limits that widen what the guard lets through (start-up parameters
// ~<limit>_ceiling, doc/ros_api.md): no limit is ever set above its ceiling, at start-up or by
// dynamic_reconfigure. The robot's own hardware limits belong here.
struct LimitCeilings {
  double max_speed = 0.1;                  // [m/s]
  double max_angular_speed = 10.0;         // [rad/s]
  double max_angular_speed_inserted = 0.5; // [rad/s]
  double max_future = 1.0;                 // [s]
  double command_timeout = 5.0;            // [s]
  double workspace_margin = 1.0;           // [m]
  // Each ceiling positive and finite (InputError: prefix + "<limit>_ceiling").
  void validate(const std::string& prefix = "") const;
  // Throws InputError naming the limit and its ceiling for a limit above it.
  void check(const CommandLimits& l, const std::string& prefix = "") const;
};

// The limits that have a ceiling: the parameter's name (its ceiling: name + "_ceiling"),
// both members and the unit. One list for the checks and the parameter readers.
struct CeiledLimit {
  const char* name;
  double LimitCeilings::*ceiling;
  double CommandLimits::*limit;
  const char* unit;
};
inline constexpr CeiledLimit kCeiledLimits[] = {
    {"max_speed", &LimitCeilings::max_speed, &CommandLimits::max_speed, "m/s"},
    {"max_angular_speed", &LimitCeilings::max_angular_speed, &CommandLimits::max_angular_speed, "rad/s"},
    {"max_angular_speed_inserted", &LimitCeilings::max_angular_speed_inserted,
     &CommandLimits::max_angular_speed_inserted, "rad/s"},
    {"max_future", &LimitCeilings::max_future, &CommandLimits::max_future, "s"},
    {"command_timeout", &LimitCeilings::command_timeout, &CommandLimits::command_timeout, "s"},
    {"workspace_margin", &LimitCeilings::workspace_margin, &CommandLimits::workspace_margin, "m"},
};

enum class GuardRule : int {
  NonFinite,        // NaN or Inf in a position or quaternion
  Quaternion,       // quaternion norm far from 1 (zero included)
  Stale,            // stamp older than command_timeout
  Future,           // stamp more than max_future ahead of now
  OutOfOrder,       // stamp older than the needle's last accepted command
  Workspace,        // position outside the tissue's box plus workspace_margin
  Frame,            // frame_id with no transform to the tissue frame (ROS layer)
  EmptyFrame,       // empty frame_id, unless allowed (ROS layer)
  Owner,            // from another source than the one that owns the needle
  Plan,             // a plan (trajectory, predict, action goal) breaking any rule: rejected whole
  LinearSpeed,      // slowed down to max_speed
  AngularSpeed,     // slowed down to max_angular_speed
  AngularInserted,  // axis turn slowed down to max_angular_speed_inserted
  kCount
};
constexpr int kGuardRules = static_cast<int>(GuardRule::kCount);
// snake_case name (status, diagnostics, warnings) and the parameter that sets it.
const char* ruleName(GuardRule r);
const char* ruleParameter(GuardRule r);
// LinearSpeed, AngularSpeed, AngularInserted slow a command down; the others reject it.
bool ruleRejects(GuardRule r);

// A base pose command as it arrives: orientation as given (not normalised; x axis along the
// needle), stamp in simulation seconds (NaN: unstamped, taken as received now).
struct PoseCommand {
  Vec3 position = Vec3::Zero();
  Eigen::Quaterniond orientation = Eigen::Quaterniond::Identity();
  double stamp = std::numeric_limits<double>::quiet_NaN();
  // Who sent it (the ROS caller id, "tf", a bag's recorded caller id): one source commands
  // a needle at a time (rule owner). "": not arbitrated (a consumer with one source).
  std::string source;
};

struct Admission {
  bool accepted = false;
  GuardRule rule = GuardRule::NonFinite;  // when rejected
  std::string reason;                     // when rejected: the rule, the value, the limit
  BasePose pose;                          // (axis, roll), roll unwrapped against the last command
  double at = 0;                          // simulation time it asks to be reached at
};

// What follow() did with a command.
struct Following {
  double reached_at = 0;  // keyframe time of the commanded pose
  bool limited = false;   // later than asked, for a limit
  GuardRule rule = GuardRule::LinearSpeed;  // the limit that set the pace, when limited
};

// One waypoint of a plan as it arrives (time from the plan's start, pose as given).
struct PlanWaypoint {
  double time = 0;
  Vec3 position = Vec3::Zero();
  Eigen::Quaterniond orientation = Eigen::Quaterniond::Identity();
  // Duty-cycled spinning over the segment from this waypoint to the next (a bevel tip's
  // variable curvature; needle/duty_cycled_spin.hpp): a fraction spin_duty in [0, 1] of the
  // segment's time turning at spin_rate [rad/s], in whole turns. 0: none.
  double spin_rate = 0;
  double spin_duty = 0;
};
using PlanPoses = std::vector<std::pair<double, BasePose>>;  // (time from start, pose)

// Rates of the base motion from pose a to pose b over a unit of time: translation [m],
// rotation and turn of the axis [rad], the rotations as the largest rate along the
// interpolated path (BaseTrajectory's interpolation, sampled); axis_turn_inside: the largest
// turn rate where `inside` says the needle is in the tissue (at either end of a sample).
struct SegmentMotion {
  double distance = 0, rotation = 0, axis_turn = 0, axis_turn_inside = 0;
};
SegmentMotion segmentMotion(const BaseTrajectory& traj, const BasePose& a, const BasePose& b,
                            const std::function<bool(const BasePose&)>& inside = {});

class CommandGuard {
 public:
  struct NeedleInfo {
    BasePose rest;         // the scene's base pose (pose convention, roll unwrapping)
    double length = 0;     // for the rigid tip position in plan checks
  };
  // Throws InputError for limits out of range or above a ceiling.
  // prefix: how its consumer names the limits in messages ("~" for the node's parameters: the
  // core's own messages name them bare, "max_speed").
  CommandGuard(const CommandLimits& limits, std::vector<NeedleInfo> needles, const LimitCeilings& ceilings = {},
               std::string prefix = "");

  // New limits (dynamic_reconfigure): validated and held to the ceilings (InputError: the
  // limits stay as they were), effective for the next command.
  void setLimits(const CommandLimits& limits);
  CommandLimits limits() const;
  const LimitCeilings& ceilings() const { return ceilings_; }

  // --- Ownership (rule owner). A needle is free, owned by a source that streams (its owner
  // until it has been silent for owner_timeout, or until the end of a plan it sent, whichever
  // is later), or held by an action or a service (until release). admit() arbitrates pose
  // commands by PoseCommand::source; a plan or an explicit hold asks here.
  // Whether `source` may command needle n at `now` (free, its own, or its owner silent past
  // the timeout); if not, counts GuardRule::Owner and says who owns it in `why`.
  bool mayCommand(int n, const std::string& source, double now, std::string& why);
  // `source` owns needle n from now, at least until `until` (a plan's end).
  void own(int n, const std::string& source, double now, double until = 0);
  // An explicit holder (the ~insert action, a service's executed plan): takes the needle when
  // mayCommand allows it, and keeps it, silent or not, until release(n, source).
  bool hold(int n, const std::string& source, double now, std::string& why);
  void release(int n, const std::string& source);
  std::string owner(int n) const;  // "" when free

  // A pose command for needle n, received at simulation time now.
  Admission admit(int n, const PoseCommand& c, double now);

  // Applies an admitted command to the needle's base trajectory at a step boundary (now:
  // the simulation time at the start of the next step, dt its length). inserted: the needle
  // is in the tissue now; the in-tissue turn limit applies then, and wherever along the
  // motion the needle's rigid tip lies in the tissue's box.
  Following follow(int n, BaseTrajectory& traj, const Admission& a, double now, double dt, bool inserted);
  // What was commanded after now, slowed down where it breaks the current limits (after a
  // setLimits that lowered them): later keyframes move later. Returns whether it changed.
  bool enforce(int n, BaseTrajectory& traj, double now, bool inserted);
  // Incremented by every setLimits (the stepping thread re-checks the trajectories then).
  long limitsVersion() const { return limits_version_.load(); }

  // Checks a plan that starts at `from` (the base pose when it starts); fills `out` with
  // the waypoints as base poses, or returns why it is refused ("waypoint k: ..."). Each
  // segment is checked over its own duration (a waypoint at the plan's start must be where
  // the base is). inserted: the needle is in the tissue now; wherever its rigid tip lies in
  // the tissue's box counts as inserted too. A segment with duty-cycled spinning becomes its
  // turns and holds in `out`, each within the angular limit. Counts GuardRule::Plan when
  // refused.
  std::string checkPlan(int n, const std::vector<PlanWaypoint>& waypoints, const BasePose& from, double dt,
                        bool inserted, PlanPoses& out);

  // After a plan was taken: the base's last commanded pose and stamp (unstamped plans do not
  // move the stamp order).
  void planTaken(int n, const BasePose& last);

  void record(GuardRule r) { ++counts_[static_cast<int>(r)]; }
  uint64_t count(GuardRule r) const { return counts_[static_cast<int>(r)].load(); }
  std::array<uint64_t, kGuardRules> counts() const;
  uint64_t rejected() const;  // commands and plans rejected, all rules
  uint64_t limited() const;   // commands slowed down
  // Back to the scene's rest poses (the stamp order starts again); the counters are kept:
  // they count over the node's lifetime.
  void restart();

 private:
  Admission reject(GuardRule r, const std::string& why);
  // checkPlan's last part: the spinning segments of a checked plan expanded in `out`.
  std::string spinPlan(const std::vector<PlanWaypoint>& w, const BaseTrajectory& shape,
                       const std::function<std::string(size_t, const std::string&)>& refuse, PlanPoses& out) const;
  // Checks position and orientation (finite, unit, workspace); converts to a base pose.
  bool checkPose(int n, const Vec3& p, const Eigen::Quaterniond& q, double roll_near, GuardRule& rule,
                 std::string& why, BasePose& pose) const;
  bool tipInTissue(int n, const BasePose& p, const CommandLimits& l) const;
  // The time the motion from `from` to `to` needs under the limits, and the limit that sets it.
  double needed(int n, const BaseTrajectory& traj, const BasePose& from, const BasePose& to, bool inserted,
                const CommandLimits& l, GuardRule& rule) const;

  // The limits' names in a message as the consumer writes them (`~` in the text: the prefix).
  std::string named(const std::string& text) const;
  std::string prefix_;
  mutable PiMutex mutex_;  // limits_, last_stamp_, last_roll_, taken_, owners_
  CommandLimits limits_;
  std::vector<NeedleInfo> needles_;
  std::vector<double> last_stamp_;  // -inf: none yet
  std::vector<double> last_roll_;
  // Per needle, the asked times of what follow() took: the last command taken at an earlier
  // step than the one under way, the first and the last taken in it (a late batch's lag and
  // the time its stream gave the motion).
  struct Taken {
    double step_now = std::numeric_limits<double>::quiet_NaN();
    double before = -std::numeric_limits<double>::infinity(), first = 0,
           last = -std::numeric_limits<double>::infinity();
  };
  std::vector<Taken> taken_;
  std::array<std::atomic<uint64_t>, kGuardRules> counts_{};
  std::atomic<long> limits_version_{0};
  LimitCeilings ceilings_;
  // Per needle, who commands it (mutex_): the source, when it last sent a command, until
  // when a plan of its keeps it, and whether it holds it explicitly.
  struct OwnerState {
    std::string source;
    double last = 0, until = 0;
    bool held = false;
  };
  std::vector<OwnerState> owners_;
  // Whether `source` may command needle n now (mutex_ held); if not, `why` names the owner.
  bool ownerAllows(int n, const std::string& source, double now, std::string& why) const;
};

}  // namespace needle_sim

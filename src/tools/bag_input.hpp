#pragma once
// A recorded session read from a rosbag (doc/cli.md, "run --bag"): the commanded base poses
// of one needle (geometry_msgs/PoseStamped, e.g. record.launch's <node>/<needle>/command_pose)
// and optionally measurements, as the node's measurement topics take them: the wrench
// (geometry_msgs/WrenchStamped in the needle's base frame, x along the needle), the tracked
// tip and a target's measured position (geometry_msgs/PointStamped), the needle's shape
// (geometry_msgs/PoseArray, the last pose at the tip), these three in the tissue frame or in
// a frame the bag's /tf and /tf_static bring into it at their stamps. Times are seconds since
// the first message on any of the topics; each measurement at its stamp (at its recording when
// unstamped).
#include <string>

#include "needle_sim/calibration/force_record.hpp"
#include "needle_sim/core/error.hpp"
#include "needle_sim/sim/command_replay.hpp"

namespace needle_sim {

struct BagTopics {
  std::string pose, wrench, tip, target, shape;  // "": not read (pose is needed)
  int target_index = 0, num_targets = 0;          // the target the target topic measures
  double shape_spacing = 5e-4;                    // [m] between a shape's poses
};

struct BagSession {
  std::vector<RecordedCommand> commands;
  // The measurements, one row per time (ForceRecord's channels): the axial force on the
  // holder [N, < 0 when the tissue resists] = wrench.force.x (NaN in rows without one), the
  // tip, the measured target, the shape (empty without their topics); empty without any.
  ForceRecord force;
  double end = 0;      // last message [s]
  double origin = 0;   // the bag's start [s since the epoch]: the times above are from here
};

// Throws InputError naming the bag and the topic: unreadable bag, an empty topic, a topic of
// another type, a topic given twice, a wrench that is not in a *_base frame, a point or shape
// in a frame the bag's tf does not bring into the tissue's at its stamp, a non-finite value, a
// shape longer than `needle_length`.
#ifdef NEEDLE_SIM_WITH_ROSBAG
BagSession readBagSession(const std::string& bag, const BagTopics& topics, int needle, double needle_length,
                          const std::string& tissue_frame = "tissue");
#else
// Built without rosbag (NEEDLE_SIM_ROS OFF and no rosbag_storage): bags are refused.
inline BagSession readBagSession(const std::string& bag, const BagTopics&, int, double, const std::string& = "tissue") {
  throw InputError(bag, "--bag", "this needle_sim was built without rosbag: read a CSV record, or build with ROS");
}
#endif

}  // namespace needle_sim

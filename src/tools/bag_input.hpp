#pragma once
// A recorded session read from a rosbag (doc/cli.md, "run --bag"): the commanded base poses
// of one needle (geometry_msgs/PoseStamped, e.g. record.launch's <node>/<needle>/command_pose)
// and optionally the measured wrench (geometry_msgs/WrenchStamped in the needle's base frame,
// x along the needle). Times are seconds since the first message on either topic.
#include <string>

#include "needle_sim/calibration/force_record.hpp"
#include "needle_sim/core/error.hpp"
#include "needle_sim/sim/command_replay.hpp"

namespace needle_sim {

struct BagSession {
  std::vector<RecordedCommand> commands;
  ForceRecord force;   // axial force on the holder [N, < 0 when the tissue resists] = wrench.force.x; empty without a wrench topic
  double end = 0;      // last message [s]
  double origin = 0;   // the bag's start [s since the epoch]: the times above are from here
};

// Throws InputError naming the bag and the topic: unreadable bag, an empty topic, a topic of
// another type, a wrench that is not in a *_base frame.
#ifdef NEEDLE_SIM_WITH_ROSBAG
BagSession readBagSession(const std::string& bag, const std::string& pose_topic, const std::string& wrench_topic,
                          int needle, const std::string& tissue_frame = "tissue");
#else
// Built without rosbag (NEEDLE_SIM_ROS OFF and no rosbag_storage): bags are refused.
inline BagSession readBagSession(const std::string& bag, const std::string&, const std::string&, int,
                                 const std::string& = "tissue") {
  throw InputError(bag, "--bag", "this needle_sim was built without rosbag: read a CSV record, or build with ROS");
}
#endif

}  // namespace needle_sim

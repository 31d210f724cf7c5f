#include "bag_input.hpp"

#include <geometry_msgs/PoseStamped.h>
#include <geometry_msgs/WrenchStamped.h>
#include <rosbag/bag.h>
#include <rosbag/view.h>

#include <cmath>
#include <limits>

#include "needle_sim/core/error.hpp"

namespace needle_sim {

BagSession readBagSession(const std::string& path, const std::string& pose_topic, const std::string& wrench_topic,
                          int needle, const std::string& tissue_frame) {
  rosbag::Bag bag;
  try {
    bag.open(path, rosbag::bagmode::Read);
  } catch (const rosbag::BagException& e) {
    throw InputError(path, "--bag", std::string("cannot read the bag: ") + e.what());
  }
  std::vector<std::string> topics{pose_topic};
  if (!wrench_topic.empty()) topics.push_back(wrench_topic);
  auto strip = [](std::string t) { return t.size() > 1 && t[0] == '/' ? t.substr(1) : t; };
  BagSession s;
  try {
    // Each topic present and of its type (rosbag keeps topics with a leading slash or not:
    // either spelling is accepted).
    for (size_t k = 0; k < topics.size(); ++k) {
      const std::string& t = topics[k];
      const std::string want = k == 0 ? "geometry_msgs/PoseStamped" : "geometry_msgs/WrenchStamped";
      rosbag::View v(bag, rosbag::TopicQuery(std::vector<std::string>{strip(t), "/" + strip(t)}));
      if (v.size() == 0) throw InputError(path, t, "no message on this topic in the bag");
      if (v.begin()->getDataType() != want)
        throw InputError(path, t, "carries " + v.begin()->getDataType() + ", not " + want);
    }
    if (!wrench_topic.empty() && strip(wrench_topic) == strip(pose_topic))
      throw InputError(path, wrench_topic, "the same topic as --pose-topic");
    std::vector<std::string> query;
    for (const auto& t : topics) query.push_back("/" + strip(t)), query.push_back(strip(t));
    rosbag::View view(bag, rosbag::TopicQuery(query));
    const ros::Time origin = view.getBeginTime();
    s.origin = origin.toSec();
    for (const rosbag::MessageInstance& m : view) {
      const double received = (m.getTime() - origin).toSec();
      s.end = std::max(s.end, received);
      if (strip(m.getTopic()) == strip(pose_topic)) {
        const auto p = m.instantiate<geometry_msgs::PoseStamped>();
        if (!p) throw InputError(path, pose_topic, "carries " + m.getDataType() + ", not geometry_msgs/PoseStamped");
        RecordedCommand c;
        c.needle = needle;
        c.received = received;
        c.command.position = Vec3(p->pose.position.x, p->pose.position.y, p->pose.position.z);
        c.command.orientation = Eigen::Quaterniond(p->pose.orientation.w, p->pose.orientation.x, p->pose.orientation.y,
                                                   p->pose.orientation.z);
        c.command.stamp = p->header.stamp.isZero() ? std::numeric_limits<double>::quiet_NaN()
                                                   : (p->header.stamp - origin).toSec();
        // Who sent it (the connection header's caller id, as the node reads it): two recorded
        // sources on one needle replay with the node's rule owner.
        c.command.source = m.getCallerId();
        if (p->header.frame_id.empty()) c.frame_rule = GuardRule::EmptyFrame;
        else if (strip(p->header.frame_id) != strip(tissue_frame)) c.frame_rule = GuardRule::Frame;
        s.commands.push_back(c);
      } else {
        const auto w = m.instantiate<geometry_msgs::WrenchStamped>();
        if (!w) throw InputError(path, wrench_topic, "carries " + m.getDataType() + ", not geometry_msgs/WrenchStamped");
        const std::string f = w->header.frame_id;
        if (f.size() < 5 || f.substr(f.size() - 5) != "_base")
          throw InputError(path, wrench_topic,
                           "the wrench is in frame '" + f + "': give it in the needle's base frame (<needle>_base, x along the needle)");
        const double t = w->header.stamp.isZero() ? received : (w->header.stamp - origin).toSec();
        if (!s.force.t.empty() && !(t > s.force.t.back())) continue;  // repeated or reordered stamps: keep the first
        s.force.t.push_back(t);
        // The sensor's reading as it is: the needle's force on the holder along the needle,
        // the simulation's axial force (observables.hpp).
        s.force.force.push_back(w->wrench.force.x);
      }
    }
  } catch (const rosbag::BagException& e) {
    throw InputError(path, "--bag", std::string("cannot read the bag: ") + e.what());
  }
  if (s.commands.empty()) throw InputError(path, pose_topic, "no message on this topic in the bag");
  if (!wrench_topic.empty() && s.force.t.size() < 2) throw InputError(path, wrench_topic, "fewer than 2 wrench messages");
  return s;
}

}  // namespace needle_sim

#include "bag_input.hpp"

#include <geometry_msgs/PointStamped.h>
#include <geometry_msgs/PoseArray.h>
#include <geometry_msgs/PoseStamped.h>
#include <geometry_msgs/WrenchStamped.h>
#include <rosbag/bag.h>
#include <rosbag/view.h>
#ifdef NEEDLE_SIM_WITH_TF2
#include <tf2/buffer_core.h>
#include <tf2/exceptions.h>
#include <tf2_msgs/TFMessage.h>
#endif

#include <algorithm>
#include <cmath>
#include <limits>
#include <memory>

#include "needle_sim/core/error.hpp"

namespace needle_sim {

#ifdef NEEDLE_SIM_WITH_TF2
namespace {
Eigen::Isometry3d isometry(const geometry_msgs::Transform& x) {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = Eigen::Quaterniond(x.rotation.w, x.rotation.x, x.rotation.y, x.rotation.z).normalized().toRotationMatrix();
  T.translation() = Vec3(x.translation.x, x.translation.y, x.translation.z);
  return T;
}
}  // namespace
#endif

BagSession readBagSession(const std::string& path, const BagTopics& topics, int needle, double needle_length,
                          const std::string& tissue_frame) {
  rosbag::Bag bag;
  try {
    bag.open(path, rosbag::bagmode::Read);
  } catch (const rosbag::BagException& e) {
    throw InputError(path, "--bag", std::string("cannot read the bag: ") + e.what());
  }
  auto strip = [](std::string t) { return t.size() > 1 && t[0] == '/' ? t.substr(1) : t; };
  // (topic, its option, its type), the pose first.
  struct Topic {
    std::string name;
    const char* option;
    const char* type;
  };
  std::vector<Topic> list{{topics.pose, "--pose-topic", "geometry_msgs/PoseStamped"}};
  if (!topics.wrench.empty()) list.push_back({topics.wrench, "--wrench-topic", "geometry_msgs/WrenchStamped"});
  if (!topics.tip.empty()) list.push_back({topics.tip, "--tip-topic", "geometry_msgs/PointStamped"});
  if (!topics.target.empty()) list.push_back({topics.target, "--target-topic", "geometry_msgs/PointStamped"});
  if (!topics.shape.empty()) list.push_back({topics.shape, "--shape-topic", "geometry_msgs/PoseArray"});
  if (!topics.shape.empty() && !(topics.shape_spacing > 0 && std::isfinite(topics.shape_spacing)))
    throw InputError(path, "--shape-spacing", "must be a positive arc length [m]");
  BagSession s;
  std::vector<MeasurementSample> measured;
  try {
    // Each topic present and of its type (rosbag keeps topics with a leading slash or not:
    // either spelling is accepted), none given twice.
    for (const Topic& t : list) {
      rosbag::View v(bag, rosbag::TopicQuery(std::vector<std::string>{strip(t.name), "/" + strip(t.name)}));
      if (v.size() == 0) throw InputError(path, t.name, "no message on this topic in the bag");
      if (v.begin()->getDataType() != t.type)
        throw InputError(path, t.name, "carries " + v.begin()->getDataType() + ", not " + t.type);
    }
    for (size_t k = 0; k < list.size(); ++k)
      for (size_t j = 0; j < k; ++j)
        if (strip(list[j].name) == strip(list[k].name))
          throw InputError(path, list[k].name, std::string("the same topic as ") + list[j].option);
    std::vector<std::string> query;
    for (const auto& t : list) query.push_back("/" + strip(t.name)), query.push_back(strip(t.name));
    rosbag::View view(bag, rosbag::TopicQuery(query));
    const ros::Time origin = view.getBeginTime();
    s.origin = origin.toSec();
    // Points measured in another frame (a tracker's, a shape sensor's) are brought into the
    // tissue frame by the bag's own /tf and /tf_static at their stamps, as the node's tf does.
#ifdef NEEDLE_SIM_WITH_TF2
    std::unique_ptr<tf2::BufferCore> tf;
    {
      rosbag::View tv(bag, rosbag::TopicQuery(std::vector<std::string>{"/tf", "tf", "/tf_static", "tf_static"}));
      if (tv.size() > 0) {
        tf = std::make_unique<tf2::BufferCore>(ros::Duration((tv.getEndTime() - tv.getBeginTime()).toSec() + 10.0));
        for (const rosbag::MessageInstance& m : tv) {
          const auto msg = m.instantiate<tf2_msgs::TFMessage>();
          if (!msg) throw InputError(path, m.getTopic(), "carries " + m.getDataType() + ", not tf2_msgs/TFMessage");
          const bool is_static = strip(m.getTopic()) == "tf_static";
          for (const auto& t : msg->transforms) tf->setTransform(t, "bag", is_static);
        }
      }
    }
#endif
    // Returns the transform that takes a point in `frame` at `stamp` into the tissue frame.
    const auto toTissue = [&](const std::string& frame, const ros::Time& stamp, double t,
                              const std::string& topic) -> Eigen::Isometry3d {
      if (frame.empty() || strip(frame) == strip(tissue_frame)) return Eigen::Isometry3d::Identity();
#ifdef NEEDLE_SIM_WITH_TF2
      if (tf) {
        try {
          return isometry(tf->lookupTransform(strip(tissue_frame), strip(frame), stamp).transform);
        } catch (const tf2::TransformException& e) {
          throw InputError(path, topic, "a measurement in frame '" + frame + "' at t = " + std::to_string(t) +
                                            " s that the bag's /tf and /tf_static do not bring into the tissue frame '" +
                                            tissue_frame + "': " + e.what());
        }
      }
#endif
      throw InputError(path, topic, "a measurement in frame '" + frame + "': the bag has no /tf or /tf_static to bring it into the tissue frame '" +
                                        tissue_frame + "'");
    };
    for (const rosbag::MessageInstance& m : view) {
      const double received = (m.getTime() - origin).toSec();
      s.end = std::max(s.end, received);
      const std::string topic = strip(m.getTopic());
      const auto at = [&](const ros::Time& stamp) { return stamp.isZero() ? received : (stamp - origin).toSec(); };
      if (topic == strip(topics.pose)) {
        const auto p = m.instantiate<geometry_msgs::PoseStamped>();
        if (!p) throw InputError(path, topics.pose, "carries " + m.getDataType() + ", not geometry_msgs/PoseStamped");
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
        if (p->header.frame_id.empty()) {
          c.frame_rule = GuardRule::EmptyFrame;
        } else if (strip(p->header.frame_id) != strip(tissue_frame)) {
          // Another frame: through the bag's tf at the pose's stamp, as the node's tf takes a
          // command; one it does not resolve is refused by rule `frame`, as the node does.
          c.frame_rule = GuardRule::Frame;
#ifdef NEEDLE_SIM_WITH_TF2
          if (tf) try {
              const auto x = tf->lookupTransform(strip(tissue_frame), strip(p->header.frame_id),
                                                 p->header.stamp.isZero() ? m.getTime() : p->header.stamp);
              const Eigen::Isometry3d T = isometry(x.transform);
              c.command.position = T * c.command.position;
              c.command.orientation = Eigen::Quaterniond(T.linear()) * c.command.orientation;
              c.frame_rule = GuardRule::NonFinite;  // (the sentinel: in the tissue frame now)
            } catch (const tf2::TransformException&) {
            }
#endif
        }
        s.commands.push_back(c);
      } else if (!topics.wrench.empty() && topic == strip(topics.wrench)) {
        const auto w = m.instantiate<geometry_msgs::WrenchStamped>();
        if (!w) throw InputError(path, topics.wrench, "carries " + m.getDataType() + ", not geometry_msgs/WrenchStamped");
        const std::string f = w->header.frame_id;
        if (f.size() < 5 || f.substr(f.size() - 5) != "_base")
          throw InputError(path, topics.wrench,
                           "the wrench is in frame '" + f + "': give it in the needle's base frame (<needle>_base, x along the needle)");
        MeasurementSample x;
        x.t = at(w->header.stamp);
        // The sensor's reading as it is: the needle's force on the holder along the needle,
        // the simulation's axial force (observables.hpp).
        x.force = w->wrench.force.x;
        measured.push_back(x);
      } else if ((!topics.tip.empty() && topic == strip(topics.tip)) || (!topics.target.empty() && topic == strip(topics.target))) {
        const bool tip = !topics.tip.empty() && topic == strip(topics.tip);
        const std::string& name = tip ? topics.tip : topics.target;
        const auto q = m.instantiate<geometry_msgs::PointStamped>();
        if (!q) throw InputError(path, name, "carries " + m.getDataType() + ", not geometry_msgs/PointStamped");
        MeasurementSample x;
        x.t = at(q->header.stamp);
        x.channel = tip ? 1 : 2;
        const Eigen::Isometry3d T = toTissue(q->header.frame_id, q->header.stamp.isZero() ? m.getTime() : q->header.stamp, x.t, name);
        x.point = T * Vec3(q->point.x, q->point.y, q->point.z);
        if (!x.point.allFinite()) throw InputError(path, name, "a non-finite position at t = " + std::to_string(x.t) + " s");
        measured.push_back(x);
      } else if (!topics.shape.empty() && topic == strip(topics.shape)) {
        const auto a = m.instantiate<geometry_msgs::PoseArray>();
        if (!a) throw InputError(path, topics.shape, "carries " + m.getDataType() + ", not geometry_msgs/PoseArray");
        MeasurementSample x;
        x.t = at(a->header.stamp);
        x.channel = 3;
        const Eigen::Isometry3d T =
            toTissue(a->header.frame_id, a->header.stamp.isZero() ? m.getTime() : a->header.stamp, x.t, topics.shape);
        const size_t n = a->poses.size();
        if (n == 0) throw InputError(path, topics.shape, "a shape without poses at t = " + std::to_string(x.t) + " s");
        if (static_cast<double>(n - 1) * topics.shape_spacing > needle_length * (1 + 1e-9))
          throw InputError(path, topics.shape, std::to_string(n) + " poses at --shape-spacing " + std::to_string(topics.shape_spacing) +
                                                   " m reach further back than the needle's " + std::to_string(needle_length) + " m");
        // The last pose is the tip: the record's points run from the tip back.
        for (size_t i = n; i-- > 0;) {
          const auto& p = a->poses[i].position;
          x.shape.push_back(T * Vec3(p.x, p.y, p.z));
          if (!x.shape.back().allFinite())
            throw InputError(path, topics.shape, "a non-finite position at t = " + std::to_string(x.t) + " s");
        }
        measured.push_back(std::move(x));
      }
    }
  } catch (const rosbag::BagException& e) {
    throw InputError(path, "--bag", std::string("cannot read the bag: ") + e.what());
  }
  if (s.commands.empty()) throw InputError(path, topics.pose, "no message on this topic in the bag");
  // Per sensor, a sample not after its previous one (a repeated or reordered stamp) is dropped
  // (the first kept); the rest laid into rows (measurementRows).
  std::stable_sort(measured.begin(), measured.end(),
                   [](const MeasurementSample& a, const MeasurementSample& b) { return a.t < b.t; });
  std::vector<MeasurementSample> kept;
  double last[4] = {-1e300, -1e300, -1e300, -1e300};
  long count[4] = {0, 0, 0, 0};
  for (MeasurementSample& x : measured) {
    if (!(x.t > last[x.channel])) continue;
    last[x.channel] = x.t;
    ++count[x.channel];
    kept.push_back(std::move(x));
  }
  s.force = measurementRows(std::move(kept), !topics.tip.empty(), topics.target.empty() ? -1 : topics.target_index,
                            topics.num_targets, !topics.shape.empty(), topics.shape_spacing);
  const std::string* names[4] = {&topics.wrench, &topics.tip, &topics.target, &topics.shape};
  for (int c = 0; c < 4; ++c)
    if (!names[c]->empty() && count[c] < 2)
      throw InputError(path, *names[c], "fewer than 2 measurements on this topic");
  return s;
}

}  // namespace needle_sim

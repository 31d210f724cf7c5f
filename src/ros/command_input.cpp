// SimulatorRos: what a robot sends. Base poses (PoseStamped on ~<needle>/command_pose, or
// tf with ~command_source tf) and plans (needle_sim/NeedleTrajectory on
// ~<needle>/command_trajectory, trajectory_msgs/MultiDOFJointTrajectory on
// ~<needle>/multi_dof_trajectory) are taken into ~tissue_frame through tf, checked by the
// core's CommandGuard and queued for the stepping thread, which applies them at the next
// step boundary. Nothing is applied here.
#include <tf2/exceptions.h>

#include "conversions.hpp"
#include "needle_sim/ros/simulator_ros.hpp"
#include "node_parameters.hpp"

namespace needle_sim {

namespace {
// A subscription whose callback gets the message and its publisher's caller id (the
// connection header's "callerid": the source for rule owner).
template <class M, class F>
ros::Subscriber subscribeWithCaller(ros::NodeHandle& nh, const std::string& topic, uint32_t queue, F f) {
  using Event = const ros::MessageEvent<M const>&;
  const boost::function<void(Event)> cb = [f](Event e) { f(e.getMessage(), e.getPublisherName()); };
  return nh.subscribe<M, Event>(topic, queue, cb);
}
}  // namespace

void SimulatorRos::subscribeCommands() {
  if (params_->command_source != "topic") return;
  for (int i = 0; i < static_cast<int>(scene_.needles.size()); ++i) {
    const std::string& name = scene_.needles[i].name;
    command_subs_.push_back(subscribeWithCaller<geometry_msgs::PoseStamped>(
        pnh_, name + "/command_pose", 100,
        [this, i](const geometry_msgs::PoseStamped::ConstPtr& m, const std::string& caller) { onPose(i, m, caller); }));
    command_subs_.push_back(subscribeWithCaller<needle_sim::NeedleTrajectory>(
        pnh_, name + "/command_trajectory", 10,
        [this, i](const needle_sim::NeedleTrajectory::ConstPtr& m, const std::string& caller) {
          onTrajectory(i, m, caller);
        }));
    command_subs_.push_back(subscribeWithCaller<trajectory_msgs::MultiDOFJointTrajectory>(
        pnh_, name + "/multi_dof_trajectory", 10,
        [this, i](const trajectory_msgs::MultiDOFJointTrajectory::ConstPtr& m, const std::string& caller) {
          onMultiDof(i, m, caller);
        }));
  }
}

void SimulatorRos::warnRule(GuardRule rule, const std::string& source, const std::string& why) {
  // At most one message per rule and second; the next one says how many it stood for.
  const ros::WallTime now = ros::WallTime::now();
  unsigned long suppressed = 0;
  {
    std::lock_guard<PiMutex> lk(warn_mutex_);
    const int r = static_cast<int>(rule);
    ros::WallTime& last = last_warning_[r];
    if (!last.isZero() && (now - last).toSec() < 1.0) {
      ++suppressed_[r];
      return;
    }
    last = now;
    suppressed = suppressed_[r];
    suppressed_[r] = 0;
  }
  const char* param = ruleParameter(rule);
  const std::string more = suppressed ? " (and " + std::to_string(suppressed) + " more by this rule since the last message)" : "";
  ROS_WARN("needle_sim: %s %s by rule '%s'%s%s%s: %s%s", source.c_str(), ruleRejects(rule) ? "rejected" : "slowed down",
           ruleName(rule), *param ? " (~" : "", param, *param ? ")" : "", why.c_str(), more.c_str());
}

bool SimulatorRos::toTissue(const std::string& frame, const ros::Time& stamp, const std::string& source, Rigid& out) {
  out = Rigid{};
  if (frame == params_->tissue_frame) return true;
  if (frame.empty()) {
    if (params_->allow_empty_frame) return true;
    guard().record(GuardRule::EmptyFrame);
    warnRule(GuardRule::EmptyFrame, source, "empty frame_id (set it to '" + params_->tissue_frame +
                                               "', or allow it with ~allow_empty_frame)");
    return false;
  }
  try {
    // The latest transform: a static one holds at any time; a moving one must not be older
    // than ~command_timeout at the command's stamp.
    const auto t = tf_buffer_->lookupTransform(params_->tissue_frame, frame, ros::Time(0));
    const double age = stamp.isZero() || t.header.stamp.isZero() ? 0.0 : (stamp - t.header.stamp).toSec();
    if (age > guard().limits().command_timeout) {
      guard().record(GuardRule::Frame);
      warnRule(GuardRule::Frame, source,
               "the transform " + params_->tissue_frame + " <- " + frame + " is " + std::to_string(age) +
                   " s older than the command");
      return false;
    }
    out = fromTransform(t.transform);
    return true;
  } catch (const tf2::TransformException& e) {
    guard().record(GuardRule::Frame);
    warnRule(GuardRule::Frame, source, "no transform " + params_->tissue_frame + " <- '" + frame + "': " + e.what());
    return false;
  }
}

void SimulatorRos::admit(int needle, const PoseCommand& c, const std::string& source) {
  std::lock_guard<PiMutex> lk(queue_mutex_);
  const double now = simSeconds(ros::Time::now());
  PoseCommand cmd = c;
  if (params_->as_fast_as_possible) cmd.stamp = std::numeric_limits<double>::quiet_NaN();  // stamps mean nothing then
  const Admission a = pipeline_->submit(needle, cmd, now);
  if (!a.accepted) warnRule(a.rule, c.source.empty() ? source : source + " from " + c.source, a.reason);
}

void SimulatorRos::onPose(int needle, const geometry_msgs::PoseStamped::ConstPtr& m, const std::string& caller) {
  const std::string source = "~" + scene_.needles[needle].name + "/command_pose";
  Rigid to_tissue;
  if (!toTissue(m->header.frame_id, m->header.stamp, source, to_tissue)) return;
  double stamp = std::numeric_limits<double>::quiet_NaN();
  if (!m->header.stamp.isZero()) {
    std::lock_guard<PiMutex> lk(queue_mutex_);
    stamp = simSeconds(m->header.stamp);
  }
  PoseCommand c = toCommand(m->pose, to_tissue, stamp);
  c.source = caller;
  admit(needle, c, source);
}

void SimulatorRos::onTrajectory(int needle, const needle_sim::NeedleTrajectory::ConstPtr& m, const std::string& caller) {
  const std::string source = "~" + scene_.needles[needle].name + "/command_trajectory from " + caller;
  Rigid to_tissue;
  if (!toTissue(m->header.frame_id, m->header.stamp, source, to_tissue)) return;
  queuePlan({needle, toWaypoints(*m, to_tissue), source, {}, caller});
}

void SimulatorRos::onMultiDof(int needle, const trajectory_msgs::MultiDOFJointTrajectory::ConstPtr& m,
                              const std::string& caller) {
  const std::string source = "~" + scene_.needles[needle].name + "/multi_dof_trajectory from " + caller;
  Rigid to_tissue;
  if (!toTissue(m->header.frame_id, m->header.stamp, source, to_tissue)) return;
  std::vector<PlanWaypoint> w;
  std::string why;
  if (!toWaypoints(*m, scene_.needles[needle].name, to_tissue, w, why)) {
    guard().record(GuardRule::Plan);
    warnRule(GuardRule::Plan, source, why);
    return;
  }
  queuePlan({needle, std::move(w), source, {}, caller});
}

void SimulatorRos::lookupTfCommands() {
  for (int i = 0; i < static_cast<int>(base_frames_.size()); ++i) {
    geometry_msgs::TransformStamped tr;
    const std::string source = "tf " + base_frames_[i];
    try {
      tr = tf_buffer_->lookupTransform(params_->tissue_frame, base_frames_[i], ros::Time(0));
    } catch (const tf2::TransformException& e) {
      // Looked up every step: an outage (or the robot not publishing yet) is one rejection,
      // not one per step.
      if (!tf_missing_[i]) {
        guard().record(GuardRule::Frame);
        warnRule(GuardRule::Frame, source, std::string("no base pose from tf: ") + e.what() + "; the base holds");
      }
      tf_missing_[i] = 1;
      continue;
    }
    tf_missing_[i] = 0;
    if (!tr.header.stamp.isZero() && tr.header.stamp == tf_last_stamp_[i]) continue;  // nothing new
    tf_last_stamp_[i] = tr.header.stamp;
    geometry_msgs::Pose p;
    p.position.x = tr.transform.translation.x;
    p.position.y = tr.transform.translation.y;
    p.position.z = tr.transform.translation.z;
    p.orientation = tr.transform.rotation;
    double stamp = std::numeric_limits<double>::quiet_NaN();
    if (!tr.header.stamp.isZero()) {
      std::lock_guard<PiMutex> lk(queue_mutex_);
      stamp = simSeconds(tr.header.stamp);
    }
    PoseCommand c = toCommand(p, Rigid{}, stamp);
    c.source = "tf";  // every base pose from tf is one source: whoever broadcasts the frame
    admit(i, c, source);
  }
}

}  // namespace needle_sim

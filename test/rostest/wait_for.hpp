#pragma once
// Shared by the rostest gtest nodes: polls a condition on the wall clock; a base pose
// command stamped now; a guard rule's count in ~status.
#include <geometry_msgs/PoseStamped.h>
#include <needle_sim/SimStatus.h>
#include <ros/ros.h>

#include <string>

namespace needle_sim_test {

template <class F>
bool waitFor(F cond, double seconds) {
  const ros::WallTime end = ros::WallTime::now() + ros::WallDuration(seconds);
  while (ros::ok() && ros::WallTime::now() < end) {
    if (cond()) return true;
    ros::WallDuration(0.01).sleep();
  }
  return cond();
}

// Needle base at (x, y, z) in the tissue frame, its axis along x (the phantom scenes' rest axis).
inline geometry_msgs::PoseStamped basePose(double x, double y, double z) {
  geometry_msgs::PoseStamped p;
  p.header.stamp = ros::Time::now();
  p.header.frame_id = "tissue";
  p.pose.position.x = x;
  p.pose.position.y = y;
  p.pose.position.z = z;
  p.pose.orientation.w = 1;
  return p;
}

// The same turned by the unit quaternion (w, x, y, z).
inline geometry_msgs::PoseStamped basePose(double x, double y, double z, double qw, double qx, double qy, double qz) {
  geometry_msgs::PoseStamped p = basePose(x, y, z);
  p.pose.orientation.w = qw, p.pose.orientation.x = qx, p.pose.orientation.y = qy, p.pose.orientation.z = qz;
  return p;
}

// The lifetime count of the command guard's rule `rule` in a ~status message; false when the
// message has no such rule.
inline bool guardCount(const needle_sim::SimStatus& s, const std::string& rule, uint64_t& n) {
  for (size_t i = 0; i < s.guard_rules.size(); ++i)
    if (s.guard_rules[i] == rule) {
      n = s.guard_counts[i];
      return true;
    }
  return false;
}

}  // namespace needle_sim_test

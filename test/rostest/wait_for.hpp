#pragma once
// Shared by the rostest gtest nodes: polls a condition on the wall clock; a base pose
// command stamped now.
#include <geometry_msgs/PoseStamped.h>
#include <ros/ros.h>

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

}  // namespace needle_sim_test

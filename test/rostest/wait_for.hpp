#pragma once
// Shared by the rostest gtest nodes: polls a condition on the wall clock.
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

}  // namespace needle_sim_test

// rostest (tf.test): ~command_source tf. The test broadcasts tissue -> needle_base advancing
// at 1 cm/s for 1 s; the node follows it (tip advanced about 10 mm, nothing rejected). When
// the transform stops changing, the base holds where it is.
#include <gtest/gtest.h>
#include <ros/ros.h>

#include "wait_for.hpp"
#include <tf2_ros/transform_broadcaster.h>

#include <cmath>
#include <mutex>

#include <nav_msgs/Path.h>
#include <needle_sim/SimStatus.h>

namespace {
std::mutex m;
double tip_x = std::nan("");
needle_sim::SimStatus status;
bool have_status = false;

using needle_sim_test::waitFor;
double tip() {
  std::lock_guard<std::mutex> lk(m);
  return tip_x;
}
}  // namespace

TEST(TfCommands, BaseFollowsTheTransform) {
  ros::NodeHandle nh("needle_sim");  // the node's private namespace
  auto s1 = nh.subscribe<nav_msgs::Path>("needle/path", 10, [&](const nav_msgs::Path::ConstPtr& p) {
    std::lock_guard<std::mutex> lk(m);
    if (!p->poses.empty()) tip_x = p->poses.back().pose.position.x;
  });
  auto s2 = nh.subscribe<needle_sim::SimStatus>("status", 10, [&](const needle_sim::SimStatus::ConstPtr& s) {
    std::lock_guard<std::mutex> lk(m);
    status = *s;
    have_status = true;
  });
  ros::AsyncSpinner spinner(2);
  spinner.start();
  ASSERT_TRUE(waitFor([] { return std::isfinite(tip()); }, 30.0));
  const double tip0 = tip();
  tf2_ros::TransformBroadcaster br;
  auto send = [&](double x) {
    geometry_msgs::TransformStamped t;
    t.header.stamp = ros::Time::now();
    t.header.frame_id = "tissue";
    t.child_frame_id = "needle_base";
    t.transform.translation.x = x;
    t.transform.translation.y = 0.01;
    t.transform.translation.z = 0.01;
    t.transform.rotation.w = 1;
    br.sendTransform(t);
  };
  // The rest pose first, until the node has it (a new tf publisher takes a moment to connect).
  for (int k = 0; k < 50; ++k) {
    send(-0.035);
    ros::WallDuration(0.01).sleep();
  }
  const ros::WallTime t0 = ros::WallTime::now();
  double x = -0.035;
  for (;;) {
    const double t = (ros::WallTime::now() - t0).toSec();
    if (t > 1.0) break;
    x = -0.035 + 0.01 * t;
    send(x);
    ros::WallDuration(0.01).sleep();
  }
  // The transform stops (stale): the base holds where it is.
  ros::WallDuration(0.5).sleep();
  const double tip1 = tip();
  EXPECT_NEAR(tip1 - tip0, 0.010, 0.0015);
  ros::WallDuration(0.5).sleep();
  EXPECT_NEAR(tip(), tip1, 2e-5);
  std::lock_guard<std::mutex> lk(m);
  EXPECT_EQ(status.state, "running");
  EXPECT_EQ(status.clamped_commands, 0u);
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "test_tf_commands");
  return RUN_ALL_TESTS();
}

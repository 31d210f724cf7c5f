// rostest (tf.test): ~command_source tf. The test broadcasts tissue -> needle_base advancing
// at 1 cm/s for 1 s; the node follows it (tip advanced about 10 mm, nothing rejected). When
// the transform stops changing, the base holds where it is. The test owns the clock
// (/use_sim_time, sim_clock.hpp): the motion is timed on simulated time, whatever the load.
#include <gtest/gtest.h>
#include <ros/ros.h>

#include "sim_clock.hpp"
#include "wait_for.hpp"
#include <tf2_ros/transform_broadcaster.h>

#include <cmath>
#include <mutex>

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
  // The tip from the status (every step), not the path (throttled by wall time).
  auto s2 = nh.subscribe<needle_sim::SimStatus>("status", 100, [&](const needle_sim::SimStatus::ConstPtr& s) {
    std::lock_guard<std::mutex> lk(m);
    status = *s;
    have_status = true;
    if (!s->tips.empty()) tip_x = s->tips[0].x;
  });
  ros::AsyncSpinner spinner(2);
  spinner.start();
  needle_sim_test::SimClock clock(nh, 0.001);  // the 8x4x4 phantom keeps the wall's pace
  ASSERT_TRUE(waitFor([] { return std::isfinite(tip()); }, 30.0));
  const double tip0 = tip();
  tf2_ros::TransformBroadcaster br;
  auto send = [&](const ros::Time& stamp, double x) {
    geometry_msgs::TransformStamped t;
    t.header.stamp = stamp;
    t.header.frame_id = "tissue";
    t.child_frame_id = "needle_base";
    t.transform.translation.x = x;
    t.transform.translation.y = 0.01;
    t.transform.translation.z = 0.01;
    t.transform.rotation.w = 1;
    br.sendTransform(t);
  };
  auto running = [] {
    std::lock_guard<std::mutex> lk(m);
    return have_status && status.state == "running";
  };
  // The rest pose first, until the node has taken it (a new tf publisher takes a moment to
  // connect, longer on a loaded machine).
  for (int k = 0; k < 3000 && !running(); ++k) {
    send(ros::Time::now(), -0.035);
    clock.sleep(0.01);
  }
  ASSERT_TRUE(running()) << "the node never took the rest pose from tf";
  // 1 cm/s for 1 s; one clock reading per sample: the pose is where the motion is at its stamp.
  const ros::Time start = ros::Time::now();
  double x = -0.035;
  for (;;) {
    const ros::Time stamp = ros::Time::now();
    const double t = (stamp - start).toSec();
    if (t > 1.0) break;
    x = -0.035 + 0.01 * t;
    send(stamp, x);
    clock.sleep(0.01);
  }
  // The last sample, then the transform stops (stale): the base holds where it is.
  send(ros::Time::now(), x);
  const double x_end = x;
  ASSERT_TRUE(waitFor(
      [&] {
        std::lock_guard<std::mutex> lk(m);
        return !status.bases.empty() && std::abs(status.bases[0].position.x - x_end) < 1e-9;
      },
      10.0))
      << "the base did not reach the last transform";
  clock.sleep(0.2);
  const double tip1 = tip();
  EXPECT_NEAR(tip1 - tip0, x_end + 0.035, 0.0015);
  EXPECT_NEAR(x_end + 0.035, 0.010, 0.0005);
  uint64_t step1;
  {
    std::lock_guard<std::mutex> lk(m);
    step1 = status.step;
  }
  ASSERT_TRUE(waitFor(
      [&] {
        std::lock_guard<std::mutex> lk(m);
        return status.step > step1 + 200;
      },
      20.0));
  EXPECT_NEAR(tip(), tip1, 2e-5);
  std::lock_guard<std::mutex> lk(m);
  EXPECT_EQ(status.state, "running");
  EXPECT_EQ(status.clamped_commands, 0u);
  // Before the first transform the lookups failed at every step: one outage, one rejection.
  EXPECT_EQ(status.rejected_commands, 1u);
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "test_tf_commands");
  return RUN_ALL_TESTS();
}

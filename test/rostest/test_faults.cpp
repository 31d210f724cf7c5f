// rostest fault checks of needle_sim_node (faults.test, issue #8). The test owns the clock
// (/use_sim_time): a thread publishes /clock in 1 ms steps of simulated time, paced at half
// the wall rate so the node keeps up on two cores.
#include <gtest/gtest.h>
#include <diagnostic_msgs/DiagnosticArray.h>
#include <ros/callback_queue.h>
#include <ros/ros.h>

#include "sim_clock.hpp"
#include "wait_for.hpp"

#include <atomic>
#include <cmath>
#include <limits>
#include <mutex>
#include <thread>
#include <vector>

#include <geometry_msgs/PoseStamped.h>
#include <geometry_msgs/WrenchStamped.h>
#include <needle_sim/SimStatus.h>
#include <sensor_msgs/PointCloud2.h>

namespace {

using needle_sim_test::waitFor;

const double kBaseX = -0.035, kY = 0.01, kZ = 0.01;  // phantom_insertion_8x4x4.yaml

geometry_msgs::PoseStamped pose(double x, double y = kY, double z = kZ) { return needle_sim_test::basePose(x, y, z); }

}  // namespace

TEST(NeedleSimFaults, BurstsNonFiniteCommandsStallsAndClockJumps) {
  ros::NodeHandle nh("needle_sim");  // the node's private namespace
  needle_sim_test::SimClock clock(nh);
  std::mutex m;
  needle_sim::SimStatus status;
  long statuses = 0;
  bool non_finite = false;
  auto s1 = nh.subscribe<needle_sim::SimStatus>("status", 1000, [&](const needle_sim::SimStatus::ConstPtr& msg) {
    std::lock_guard<std::mutex> lk(m);
    status = *msg;
    ++statuses;
    non_finite = non_finite || !std::isfinite(msg->step_ms);
  });
  auto s2 = nh.subscribe<geometry_msgs::WrenchStamped>("needle/wrench", 1000, [&](const geometry_msgs::WrenchStamped::ConstPtr& w) {
    std::lock_guard<std::mutex> lk(m);
    const auto& f = w->wrench.force;
    non_finite = non_finite || !std::isfinite(f.x) || !std::isfinite(f.y) || !std::isfinite(f.z);
  });
  auto last = [&] {
    std::lock_guard<std::mutex> lk(m);
    return status;
  };
  // Diagnostics: the node's "simulation" status, every one seen after the bad commands.
  std::vector<std::pair<int, std::string>> diags;
  bool after_bad = false;
  auto s4 = nh.subscribe<diagnostic_msgs::DiagnosticArray>("/diagnostics", 100, [&](const diagnostic_msgs::DiagnosticArray::ConstPtr& d) {
    std::lock_guard<std::mutex> lk(m);
    for (const auto& st : d->status)
      if (after_bad && st.name.find("simulation") != std::string::npos) diags.emplace_back(st.level, st.message);
  });
  ros::Publisher cmd = nh.advertise<geometry_msgs::PoseStamped>("needle/command_pose", 20000);
  ros::AsyncSpinner spinner(2);
  spinner.start();
  ASSERT_TRUE(waitFor([&] { std::lock_guard<std::mutex> lk(m); return statuses > 10; }, 30.0));
  ASSERT_TRUE(waitFor([&] { return cmd.getNumSubscribers() > 0; }, 10.0));

  // 1. NaN and Inf poses: each rejected and counted; nothing else happens.
  const auto r0 = last().rejected_commands;
  const double bad[] = {std::numeric_limits<double>::quiet_NaN(), std::numeric_limits<double>::infinity(),
                        -std::numeric_limits<double>::infinity()};
  int sent = 0;
  for (double b : bad)
    for (int axis = 0; axis < 3; ++axis) {
      auto p = pose(kBaseX);
      (axis == 0 ? p.pose.position.x : axis == 1 ? p.pose.position.y : p.pose.position.z) = b;
      cmd.publish(p);
      ++sent;
    }
  auto q = pose(kBaseX);
  q.pose.orientation.w = std::numeric_limits<double>::quiet_NaN();
  cmd.publish(q);
  ++sent;
  ASSERT_TRUE(waitFor([&] { return last().rejected_commands == r0 + sent; }, 10.0)) << last().rejected_commands - r0;
  EXPECT_EQ(last().state, "waiting");  // nothing accepted yet
  {
    std::lock_guard<std::mutex> lk(m);
    after_bad = true;
  }
  // Reported through diagnostics: a WARN naming the rejected commands (the updater runs
  // once per second of the simulated clock, which runs at half the wall clock here).
  ASSERT_TRUE(waitFor([&] {
    std::lock_guard<std::mutex> lk(m);
    for (const auto& [level, msg] : diags)
      if (level == diagnostic_msgs::DiagnosticStatus::WARN && msg.find("rejected") != std::string::npos) return true;
    return false;
  }, 15.0)) << "no WARN diagnostic after rejected commands";

  // 2. A burst of 10,000 commands (toward the tissue, 1 mm in all) as fast as they can go:
  //    dropped by the queue or clamped, never a failure; the steps go on.
  const auto before = last();
  for (int i = 0; i < 10000; ++i) cmd.publish(pose(kBaseX + 1e-7 * i));
  ASSERT_TRUE(waitFor([&] { return last().step > before.step + 500; }, 20.0));
  EXPECT_EQ(last().state, "running");  // commands accepted

  // 3. A subscriber of the heavy outputs that stalls (its callback sleeps): the node's
  //    step rate does not depend on it (outgoing queues drop instead of blocking).
  std::atomic<int> clouds{0};
  ros::NodeHandle slow_nh("needle_sim");
  ros::CallbackQueue slow_queue;
  slow_nh.setCallbackQueue(&slow_queue);
  auto s3 = slow_nh.subscribe<sensor_msgs::PointCloud2>("tissue/deformation", 1, [&](const sensor_msgs::PointCloud2::ConstPtr&) {
    ++clouds;
    ros::WallDuration(1.0).sleep();
  });
  std::thread slow([&] {
    for (int k = 0; k < 3; ++k) slow_queue.callAvailable(ros::WallDuration(1.0));
  });
  const auto a = last();
  const long clock_a = clock.ms;
  ros::WallDuration(2.0).sleep();
  const auto b = last();
  const long clock_b = clock.ms;
  slow.join();
  s3.shutdown();
  EXPECT_GT(clouds.load(), 0);
  std::cout << "while a subscriber stalled: " << b.step - a.step << " steps in " << clock_b - clock_a
            << " ms of the clock (ratio " << static_cast<double>(b.step - a.step) / (clock_b - clock_a) << ", at least 0.6)\n";
  // The node keeps up with the clock (about 500 steps per wall second, fewer on a loaded
  // machine): a node blocked by the stalled subscriber would fall about 500 steps behind
  // per stalled second (of the 2 s measured).
  EXPECT_GT(static_cast<double>(b.step - a.step), 0.6 * static_cast<double>(clock_b - clock_a))
      << "steps while a subscriber stalled; the clock advanced " << clock_b - clock_a << " ms";

  // 4. Time jumps backwards (a bag in a loop): the scene restarts and runs on.
  const auto c = last();
  ASSERT_GT(c.step, 1000u);
  clock.ms = 1000;
  ASSERT_TRUE(waitFor([&] { return last().step < c.step / 2; }, 10.0)) << last().step;
  ASSERT_TRUE(waitFor([&] { return last().step > 100; }, 10.0));
  EXPECT_EQ(last().state, "waiting");  // a new run: no command since
  EXPECT_EQ(last().rejected_commands, c.rejected_commands);  // lifetime counts: kept by the restart

  std::lock_guard<std::mutex> lk(m);
  EXPECT_FALSE(non_finite) << "a non-finite value was published";
  for (const auto& [level, msg] : diags) EXPECT_NE(level, diagnostic_msgs::DiagnosticStatus::ERROR) << msg;
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "test_faults");
  return RUN_ALL_TESTS();
}

// rostest (guard.test): the command guard of the real node, under a clock owned by the test
// (1 ms of /clock per 2 ms of wall time), phantom 8x4x4, commands on ~needle/command_pose.
// Each rule: a command that breaks it is rejected or slowed down, counted under its name in
// ~status; the base (~status bases, every step) never moves faster than the linear and
// angular limits: a future stamp followed by normal commands, a non-unit quaternion, a jump
// after a 2 s pause, a 120 degree turn, a 90 degree turn of the axis with the needle in the
// tissue. Poses in another frame are followed through tf; without a transform, or with an
// empty frame, they are rejected.
#include <gtest/gtest.h>
#include <ros/ros.h>
#include <tf2_ros/static_transform_broadcaster.h>

#include <Eigen/Geometry>
#include <atomic>
#include <cmath>
#include <mutex>
#include <thread>
#include <vector>

#include <geometry_msgs/PoseStamped.h>
#include <needle_sim/SimStatus.h>

#include "sim_clock.hpp"
#include "status_recorder.hpp"
#include "wait_for.hpp"

namespace {

using needle_sim_test::waitFor;
const double kBaseX = -0.035, kY = 0.01, kZ = 0.01;  // phantom_insertion_8x4x4.yaml
const double kMaxSpeed = 0.05, kMaxAngular = 1.0, kMaxInserted = 0.1;  // the node's defaults

struct Sample {
  uint64_t step;
  double t;
  Eigen::Vector3d base;
  Eigen::Quaterniond q;
  std::string insertion;
};

struct Recorder : needle_sim_test::StatusRecorder<Sample> {
  void on(const needle_sim::SimStatus::ConstPtr& s) {
    std::lock_guard<std::mutex> lk(m);
    last = *s;
    if (s->bases.empty()) return;
    const auto& p = s->bases[0];
    samples.push_back({s->step, s->sim_time, Eigen::Vector3d(p.position.x, p.position.y, p.position.z),
                       Eigen::Quaterniond(p.orientation.w, p.orientation.x, p.orientation.y, p.orientation.z),
                       s->insertion_states.empty() ? "" : s->insertion_states[0]});
  }
  // Largest base speeds (linear, angular, axis turn) between consecutive steps since sample k.
  void rates(size_t k, double& lin, double& ang, double& axis) {
    std::lock_guard<std::mutex> lk(m);
    lin = ang = axis = 0;
    for (size_t i = std::max<size_t>(k, 1); i < samples.size(); ++i) {
      const Sample &a = samples[i - 1], &b = samples[i];
      const double dt = b.t - a.t;
      if (b.step != a.step + 1 || dt <= 0) continue;
      lin = std::max(lin, (b.base - a.base).norm() / dt);
      ang = std::max(ang, b.q.angularDistance(a.q) / dt);
      const Eigen::Vector3d xa = a.q * Eigen::Vector3d::UnitX(), xb = b.q * Eigen::Vector3d::UnitX();
      axis = std::max(axis, std::acos(std::clamp(xa.dot(xb), -1.0, 1.0)) / dt);
    }
  }
};

geometry_msgs::PoseStamped pose(double x, double y = kY, double z = kZ,
                                const Eigen::Quaterniond& q = Eigen::Quaterniond::Identity()) {
  return needle_sim_test::basePose(x, y, z, q.w(), q.x(), q.y(), q.z());
}

using needle_sim_test::simWait;

}  // namespace

TEST(CommandGuard, EveryRuleRejectsOrSlowsDownAndTheBaseNeverMovesFasterThanTheLimits) {
  ros::NodeHandle nh("needle_sim");
  needle_sim_test::SimClock clock(nh);
  Recorder rec;
  auto sub = nh.subscribe<needle_sim::SimStatus>("status", 5000, [&](const needle_sim::SimStatus::ConstPtr& s) { rec.on(s); });
  ros::Publisher cmd = nh.advertise<geometry_msgs::PoseStamped>("needle/command_pose", 1000);
  tf2_ros::StaticTransformBroadcaster static_tf;
  // world -> tissue (+10 cm in x) for part 6, sent now: the node has it by then, however
  // slowly its tf listener connects (a static transform is latched).
  geometry_msgs::TransformStamped w;
  w.header.stamp = ros::Time::now();
  w.header.frame_id = "world";
  w.child_frame_id = "tissue";
  w.transform.translation.x = 0.1;
  w.transform.rotation.w = 1;
  static_tf.sendTransform(w);
  ros::AsyncSpinner spinner(2);
  spinner.start();
  ASSERT_TRUE(waitFor([&] { return rec.size() > 20; }, 30.0));
  ASSERT_TRUE(waitFor([&] { return cmd.getNumSubscribers() > 0; }, 10.0));
  // No command yet: waiting (topic commands), stepping all the same.
  EXPECT_EQ(rec.status().state, "waiting");

  // 1. A command stamped 10 s ahead: rejected (future); the normal commands after it, a
  //    stream of 2 mm at 10 mm/s, are followed on time.
  cmd.publish(pose(kBaseX));
  ASSERT_TRUE(waitFor([&] { return rec.status().state == "running"; }, 5.0));
  auto ahead = pose(kBaseX - 0.001);
  ahead.header.stamp = ros::Time::now() + ros::Duration(10.0);
  cmd.publish(ahead);
  ASSERT_TRUE(waitFor([&] { return rec.count("future") == 1; }, 5.0));
  const ros::Time s0 = ros::Time::now();
  for (;;) {
    const double t = (ros::Time::now() - s0).toSec();
    if (t > 0.2) break;
    cmd.publish(pose(kBaseX - 0.01 * t));
    ros::WallDuration(0.004).sleep();
  }
  const double end_x = kBaseX - 0.01 * (ros::Time::now() - s0).toSec();
  ASSERT_TRUE(simWait(rec, 0.03));  // stamp + 5 ms latency, and some
  EXPECT_NEAR(rec.lastSample().base.x(), end_x, 2e-4) << "the stream after a future stamp is followed on time";
  EXPECT_EQ(rec.count("linear_speed"), 0u);

  // 2. Out of order, and a non-unit quaternion (2, 2, 2, 2): rejected, nothing moves.
  const Sample before = rec.lastSample();
  auto old = pose(kBaseX + 0.002);
  old.header.stamp = ros::Time::now() - ros::Duration(0.1);
  cmd.publish(old);
  ASSERT_TRUE(waitFor([&] { return rec.count("out_of_order") == 1; }, 5.0));
  cmd.publish(pose(before.base.x(), kY, kZ, Eigen::Quaterniond(2, 2, 2, 2)));
  ASSERT_TRUE(waitFor([&] { return rec.count("quaternion_norm") == 1; }, 5.0));
  ASSERT_TRUE(simWait(rec, 0.05));
  EXPECT_LT((rec.lastSample().base - before.base).norm(), 1e-9);
  EXPECT_LT(rec.lastSample().q.angularDistance(before.q), 1e-9);

  // 3. 2 s of silence, then one command 20 mm away: approached at the limit (0.4 s), not
  //    jumped to.
  ASSERT_TRUE(simWait(rec, 2.0));
  size_t mark = rec.size();
  const Eigen::Vector3d from = rec.lastSample().base;
  cmd.publish(pose(from.x() - 0.02));
  ASSERT_TRUE(waitFor([&] { return rec.count("linear_speed") == 1; }, 5.0));
  ASSERT_TRUE(simWait(rec, 0.2));
  EXPECT_GT((rec.lastSample().base - from).norm(), 0.005) << "moving";
  EXPECT_LT((rec.lastSample().base - from).norm(), 0.015) << "but not there yet after 0.2 s";
  ASSERT_TRUE(simWait(rec, 0.35));
  EXPECT_NEAR(rec.lastSample().base.x(), from.x() - 0.02, 1e-9);
  double lin, ang, axis;
  rec.rates(mark, lin, ang, axis);
  EXPECT_LE(lin, kMaxSpeed * (1 + 1e-6));
  EXPECT_GT(lin, 0.9 * kMaxSpeed);

  // 4. A turn of 120 degrees at once (the needle in free space): at most 1 rad/s.
  mark = rec.size();
  const double bx = rec.lastSample().base.x();
  const Eigen::Quaterniond turn(Eigen::AngleAxisd(2 * M_PI / 3, Eigen::Vector3d(1, 1, 1).normalized()));
  cmd.publish(pose(bx, kY, kZ, turn));
  ASSERT_TRUE(waitFor([&] { return rec.count("angular_speed") == 1; }, 5.0));
  ASSERT_TRUE(simWait(rec, 2.3));
  EXPECT_LT(rec.lastSample().q.angularDistance(turn), 1e-6);
  cmd.publish(pose(bx, kY, kZ));  // and back
  ASSERT_TRUE(simWait(rec, 2.3));
  EXPECT_LT(rec.lastSample().q.angularDistance(Eigen::Quaterniond::Identity()), 1e-6);
  rec.rates(mark, lin, ang, axis);
  EXPECT_LE(ang, kMaxAngular * 1.01);
  EXPECT_GT(ang, 0.8 * kMaxAngular);

  // 5. Inserted 8 mm (tip 5 mm into the tissue) at 10 mm/s, then a 90 degree turn of the axis:
  //    at most 0.1 rad/s while the needle is in the tissue.
  const ros::Time i0 = ros::Time::now();
  const double x0 = bx;
  double x = x0;
  for (;;) {
    const double t = (ros::Time::now() - i0).toSec();
    x = std::min(kBaseX + 0.008, x0 + 0.01 * t);
    cmd.publish(pose(x));
    if (x >= kBaseX + 0.008) break;
    ros::WallDuration(0.004).sleep();
  }
  ASSERT_TRUE(simWait(rec, 0.2));
  ASSERT_EQ(rec.lastSample().insertion, "inserted");
  mark = rec.size();
  const Eigen::Quaterniond tilt(Eigen::AngleAxisd(M_PI / 2, Eigen::Vector3d::UnitZ()));
  cmd.publish(pose(x, kY, kZ, tilt));
  ASSERT_TRUE(waitFor([&] { return rec.count("angular_speed_inserted") == 1; }, 5.0));
  ASSERT_TRUE(simWait(rec, 0.5));
  cmd.publish(pose(x));  // stop the turn: back to the axis
  ASSERT_TRUE(simWait(rec, 1.0));
  rec.rates(mark, lin, ang, axis);
  EXPECT_LE(axis, kMaxInserted * 1.01);
  EXPECT_GT(axis, 0.5 * kMaxInserted);
  EXPECT_EQ(rec.status().state, "running");

  // 6. Frames: a pose in `world` (world -> tissue: +10 cm in x, static) is followed in the
  //    tissue frame; a frame without a transform and an empty frame are rejected.
  auto in_world = pose(x - 0.001 + 0.1);
  in_world.header.frame_id = "world";
  in_world.header.stamp = ros::Time::now();
  cmd.publish(in_world);
  ASSERT_TRUE(simWait(rec, 0.1));
  EXPECT_NEAR(rec.lastSample().base.x(), x - 0.001, 1e-9) << "followed in the tissue frame";
  EXPECT_EQ(rec.count("frame"), 0u);
  auto nowhere = pose(x);
  nowhere.header.frame_id = "nowhere";
  cmd.publish(nowhere);
  ASSERT_TRUE(waitFor([&] { return rec.count("frame") == 1; }, 5.0));
  auto empty = pose(x);
  empty.header.frame_id = "";
  cmd.publish(empty);
  ASSERT_TRUE(waitFor([&] { return rec.count("empty_frame") == 1; }, 5.0));
  ASSERT_TRUE(simWait(rec, 0.05));
  EXPECT_NEAR(rec.lastSample().base.x(), x - 0.001, 1e-9) << "nothing moved";

  // Every rejection counted once, the slow-downs apart.
  const auto st = rec.status();
  EXPECT_EQ(st.rejected_commands, 5u);  // future, out_of_order, quaternion_norm, frame, empty_frame
  EXPECT_EQ(st.clamped_commands, rec.count("linear_speed") + rec.count("angular_speed") +
                                     rec.count("angular_speed_inserted"));
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "test_guard");
  return RUN_ALL_TESTS();
}

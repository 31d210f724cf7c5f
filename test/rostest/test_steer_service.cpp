// rostest of bevel steering through the node (steer.test: the phantom with a 30 degree bevel,
// the tissue 0.1 m along x in `world`): ~steer refuses what it cannot plan with the reason,
// plans a roll-flip to a target given in `world` within the tolerance, and, executed, the
// live tip ends where the plan's prediction said; the status reports the bevel's direction
// and the cut path's curvature; a NeedleTrajectory with duty-cycled spinning is checked (a
// duty outside [0, 1] is refused and counted) and turns the base a whole turn.
#include <gtest/gtest.h>
#include <ros/ros.h>

#include <cmath>
#include <mutex>
#include <string>

#include <needle_sim/NeedleTrajectory.h>
#include <needle_sim/SimStatus.h>
#include <needle_sim/SteerToTarget.h>

#include "wait_for.hpp"

namespace {

using needle_sim_test::waitFor;

struct StatusListener {
  std::mutex m;
  needle_sim::SimStatus last;
  bool have = false;
  double min_base_y_axis_y = 2;  // lowest y component of the base frame's y axis seen (spin check)
  bool watch_spin = false;
  ros::Subscriber sub;
  explicit StatusListener(ros::NodeHandle& nh) {
    sub = nh.subscribe<needle_sim::SimStatus>("status", 100, [this](const needle_sim::SimStatus::ConstPtr& s) {
      std::lock_guard<std::mutex> lk(m);
      last = *s;
      have = true;
      if (watch_spin && !s->bases.empty()) {
        const auto& q = s->bases[0].orientation;
        // y component of R(q) e_y
        const double yy = 1 - 2 * (q.x * q.x + q.z * q.z);
        min_base_y_axis_y = std::min(min_base_y_axis_y, yy);
      }
    });
  }
  needle_sim::SimStatus status() {
    std::lock_guard<std::mutex> lk(m);
    return last;
  }
  uint64_t count(const std::string& rule) {
    const needle_sim::SimStatus s = status();
    for (size_t i = 0; i < s.guard_rules.size(); ++i)
      if (s.guard_rules[i] == rule) return s.guard_counts[i];
    return 0;
  }
};

needle_sim::SteerToTarget request(double x, double y, double z, const std::string& frame = "world") {
  needle_sim::SteerToTarget s;
  s.request.target.header.frame_id = frame;
  s.request.target.point.x = x;
  s.request.target.point.y = y;
  s.request.target.point.z = z;
  return s;
}

}  // namespace

TEST(SteerService, RefusesWhatItCannotPlanAndPlansRunsARollFlip) {
  ros::NodeHandle nh("needle_sim");
  StatusListener listen(nh);
  ASSERT_TRUE(ros::service::waitForService("needle_sim/steer", 20000));
  ASSERT_TRUE(waitFor([&] { return listen.have; }, 20));

  // Refused, each naming what is wrong.
  auto refused = [](needle_sim::SteerToTarget s, const std::string& key) {
    EXPECT_TRUE(ros::service::call("needle_sim/steer", s));
    EXPECT_FALSE(s.response.success) << key;
    EXPECT_NE(s.response.message.find(key), std::string::npos) << s.response.message;
  };
  {
    auto s = request(0.118, 0.0099, 0.01);
    s.request.needle = "nope";
    refused(s, "needle");
  }
  refused(request(0.118, 0.0099, 0.01, "nowhere"), "frame");
  refused(request(0.15, 0.01, 0.01), "steer.target");  // beyond the 40 mm block
  {
    auto s = request(0.118, 0.0099, 0.01);
    s.request.speed = -1;
    refused(s, "speed");
    s.request.speed = 0.2;  // above ~max_speed (0.05 m/s)
    refused(s, "max_speed");
    s.request.speed = 0;
    s.request.roll_rate = 10;  // above ~max_angular_speed (7 rad/s)
    refused(s, "max_angular_speed");
  }

  // A target 0.1 mm below the axis at 18 mm (world x 0.118 is tissue x 0.018): the full arc
  // overshoots, the plan flips. Predicted at the scene's own step, so that the live run can
  // be compared with it.
  auto s = request(0.118, 0.0099, 0.0100);
  s.request.dt = 0.001;
  s.request.tolerance = 5e-5;
  ASSERT_TRUE(ros::service::call("needle_sim/steer", s));
  const auto& r = s.response;
  ASSERT_TRUE(r.success) << r.message;
  EXPECT_TRUE(r.reached) << r.message;
  EXPECT_FALSE(r.executed);
  EXPECT_LT(r.predicted_distance, 5e-5);
  EXPECT_TRUE(std::isfinite(r.flip_depth));
  EXPECT_LT(r.flip_depth, r.advance);
  EXPECT_GT(r.curvature, 0);
  EXPECT_EQ(r.plan.header.frame_id, "tissue");
  EXPECT_GE(r.plan.waypoints.size(), 4u);
  EXPECT_LE(r.iteration_distances.size(), 8u);
  EXPECT_NEAR(r.predicted_tip.x, 0.018, 5e-5);  // tissue frame
  const double plan_s = r.plan.waypoints.back().time_from_start.toSec();
  ROS_INFO("steer: %s; plan %.2f s, flip at %.3f mm of %.3f mm", r.message.c_str(), plan_s, 1e3 * r.flip_depth,
           1e3 * r.advance);

  // Executed: the same plan (the node has not moved) runs live; the tip ends where predicted.
  s.request.execute = true;
  ASSERT_TRUE(ros::service::call("needle_sim/steer", s));
  ASSERT_TRUE(r.executed) << r.message;
  const double t0 = listen.status().sim_time;
  ASSERT_TRUE(waitFor([&] { return listen.status().sim_time > t0 + plan_s + 0.5; }, 4 * plan_s + 30));
  const needle_sim::SimStatus st = listen.status();
  EXPECT_EQ(st.state, "running");
  ASSERT_EQ(st.tips.size(), 1u);
  const double dx = st.tips[0].x - r.predicted_tip.x, dy = st.tips[0].y - r.predicted_tip.y,
               dz = st.tips[0].z - r.predicted_tip.z;
  const double off = std::sqrt(dx * dx + dy * dy + dz * dz);
  ROS_INFO("steer: live tip %.4f mm from the prediction", 1e3 * off);
  EXPECT_LT(off, 5e-5);
  EXPECT_EQ(listen.count("plan"), 0u);
  // The bevel's direction (unit, across the axis) and the cut path's curvature are reported.
  ASSERT_EQ(st.bevel_directions.size(), 1u);
  ASSERT_EQ(st.path_curvatures.size(), 1u);
  const auto& b = st.bevel_directions[0];
  EXPECT_NEAR(std::sqrt(b.x * b.x + b.y * b.y + b.z * b.z), 1.0, 1e-6);
  EXPECT_LT(std::abs(b.x), 0.1);
  EXPECT_TRUE(std::isfinite(st.path_curvatures[0]));

  // Duty-cycled spinning: a duty outside [0, 1] is refused whole and counted.
  ros::Publisher traj = nh.advertise<needle_sim::NeedleTrajectory>("needle/command_trajectory", 10);
  ASSERT_TRUE(waitFor([&] { return traj.getNumSubscribers() > 0; }, 10));
  const geometry_msgs::Pose base = st.bases[0];
  auto spinPlan = [&](double duty) {
    needle_sim::NeedleTrajectory m;
    m.header.frame_id = "tissue";
    m.header.stamp = ros::Time::now();
    needle_sim::NeedleWaypoint a, e;
    a.time_from_start = ros::Duration(0.2);
    a.pose = base;
    a.spin_rate = 2 * M_PI;
    a.spin_duty = duty;
    e.time_from_start = ros::Duration(2.2);
    e.pose = base;
    e.pose.position.x += 0.002;
    m.waypoints = {a, e};
    return m;
  };
  const uint64_t plans0 = listen.count("plan");
  traj.publish(spinPlan(1.5));
  EXPECT_TRUE(waitFor([&] { return listen.count("plan") == plans0 + 1; }, 5));
  // A valid one (half the time spinning at one turn a second over 2 s: one whole turn) is
  // taken, and the base's y axis points to -y half way round.
  {
    std::lock_guard<std::mutex> lk(listen.m);
    listen.watch_spin = true;
  }
  const double y0 = [&] {
    const auto& q = base.orientation;
    return 1 - 2 * (q.x * q.x + q.z * q.z);
  }();
  traj.publish(spinPlan(0.5));
  const double t1 = listen.status().sim_time;
  ASSERT_TRUE(waitFor([&] { return listen.status().sim_time > t1 + 3.0; }, 40));
  EXPECT_EQ(listen.count("plan"), plans0 + 1);
  {
    std::lock_guard<std::mutex> lk(listen.m);
    EXPECT_LT(listen.min_base_y_axis_y, -0.9) << "the base never turned half way (y axis y " << y0 << " at the start)";
  }
  const needle_sim::SimStatus end = listen.status();
  EXPECT_EQ(end.state, "running");
  EXPECT_NEAR(end.bases[0].position.x, base.position.x + 0.002, 1e-6);
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "test_steer_service");
  ros::AsyncSpinner spinner(1);  // the status callbacks while the test waits and calls
  spinner.start();
  return RUN_ALL_TESTS();
}

// rostest behaviour checks of needle_sim_node (launched by node.test with the phantom
// insertion scene, commands from needle/command_pose): commanded insertion moves the tip
// and punctures, the wrench opposes the insertion, bad commands are rejected while the node
// keeps running, the deformation cloud is well formed, reset restores the initial state,
// set_target adds a tracked target (target/state, target, tf) and rejects one outside,
// predict simulates a plan on a copy without moving the live needle. The test owns the
// clock (/use_sim_time, sim_clock.hpp): commands, holds and plans are timed on simulated time,
// so a loaded machine slows the test down but does not change what it measures.
#include <gtest/gtest.h>
#include <ros/ros.h>

#include "sim_clock.hpp"
#include "wait_for.hpp"

#include <atomic>
#include <cmath>
#include <map>
#include <mutex>

#include <geometry_msgs/PoseStamped.h>
#include <geometry_msgs/WrenchStamped.h>
#include <nav_msgs/Path.h>
#include <geometry_msgs/PointStamped.h>
#include <needle_sim/NeedleTrajectory.h>
#include <needle_sim/PredictInsertion.h>
#include <needle_sim/SetTarget.h>
#include <needle_sim/TargetState.h>
#include <tf2_ros/buffer.h>
#include <tf2_ros/transform_listener.h>
#include <needle_sim/SimStatus.h>
#include <sensor_msgs/PointCloud2.h>
#include <sensor_msgs/point_cloud2_iterator.h>
#include <std_srvs/Trigger.h>
#include <diagnostic_msgs/DiagnosticArray.h>
#include <visualization_msgs/MarkerArray.h>

namespace {

struct Listener {
  std::mutex m;
  needle_sim::SimStatus status;
  bool have_status = false;
  nav_msgs::Path path;
  bool have_path = false;
  std::vector<double> wrench_x;
  sensor_msgs::PointCloud2 cloud;
  bool have_cloud = false;

  double tipX() {
    std::lock_guard<std::mutex> lk(m);
    return path.poses.empty() ? std::nan("") : path.poses.back().pose.position.x;
  }
  needle_sim::SimStatus lastStatus() {
    std::lock_guard<std::mutex> lk(m);
    return status;
  }
};

using needle_sim_test::waitFor;

const double kBaseX = -0.035, kY = 0.01, kZ = 0.01;  // phantom_insertion_8x4x4.yaml

geometry_msgs::PoseStamped pose(double x, double y = kY, double z = kZ) { return needle_sim_test::basePose(x, y, z); }

}  // namespace

TEST(NeedleSimNode, CommandedInsertionRejectsBadCommandsAndResets) {
  ros::NodeHandle nh("needle_sim");  // the node's private namespace
  Listener L;
  auto s1 = nh.subscribe<needle_sim::SimStatus>("status", 100, [&](const needle_sim::SimStatus::ConstPtr& m) {
    std::lock_guard<std::mutex> lk(L.m);
    L.status = *m;
    L.have_status = true;
  });
  auto s2 = nh.subscribe<nav_msgs::Path>("needle/path", 10, [&](const nav_msgs::Path::ConstPtr& m) {
    std::lock_guard<std::mutex> lk(L.m);
    L.path = *m;
    L.have_path = true;
  });
  auto s3 = nh.subscribe<geometry_msgs::WrenchStamped>("needle/wrench", 1000, [&](const geometry_msgs::WrenchStamped::ConstPtr& m) {
    std::lock_guard<std::mutex> lk(L.m);
    L.wrench_x.push_back(m->wrench.force.x);
  });
  ros::Publisher cmd = nh.advertise<geometry_msgs::PoseStamped>("needle/command_pose", 100);
  ros::AsyncSpinner spinner(2);
  spinner.start();
  needle_sim_test::SimClock clock(nh, 0.001);  // the 8x4x4 phantom keeps the wall's pace

  ASSERT_TRUE(waitFor([&] { std::lock_guard<std::mutex> lk(L.m); return L.have_status && L.have_path; }, 30.0));
  ASSERT_TRUE(waitFor([&] { return cmd.getNumSubscribers() > 0; }, 10.0));
  const double tip0 = L.tipX();
  EXPECT_NEAR(tip0, -0.003, 1e-6);

  // 1. Insertion at 1 cm/s for 1.5 s (puncture after 0.3 s), commands every 5 ms of
  //    simulated time.
  const ros::Time t0 = ros::Time::now();
  size_t wrench_mark = 0;
  for (;;) {
    const double t = (ros::Time::now() - t0).toSec();
    if (t > 1.5) break;
    if (t > 1.0 && wrench_mark == 0) {
      std::lock_guard<std::mutex> lk(L.m);
      wrench_mark = L.wrench_x.size();
    }
    cmd.publish(pose(kBaseX + 0.01 * t));
    clock.sleep(0.005);
  }
  cmd.publish(pose(kBaseX + 0.015));  // the end of the motion, 1.5 s (or a few ms more) after its start
  clock.sleep(0.3);
  // The base went 15 mm; the tip follows it, less the needle's compression against the
  // tissue (14.996 mm measured).
  const double tip1 = L.tipX();
  std::cout << "tip advanced " << tip1 - tip0 << " m\n";
  EXPECT_GT(tip1 - tip0, 0.0148) << "tip advanced " << tip1 - tip0;
  EXPECT_LT(tip1 - tip0, 0.01505);
  needle_sim::SimStatus st = L.lastStatus();
  ASSERT_EQ(st.insertion_states.size(), 1u);
  EXPECT_TRUE(st.insertion_states[0] == "inserted" || st.insertion_states[0] == "punctured") << st.insertion_states[0];
  EXPECT_GT(st.constraint_points, 0u);
  EXPECT_EQ(st.state, "running");
  {
    std::lock_guard<std::mutex> lk(L.m);
    ASSERT_GT(L.wrench_x.size(), wrench_mark + 10);
    double mean = 0;
    for (size_t k = wrench_mark; k < L.wrench_x.size(); ++k) mean += L.wrench_x[k];
    mean /= L.wrench_x.size() - wrench_mark;
    EXPECT_LT(mean, 0.0) << "the needle pushes back on its holder while it cuts its way in";
  }

  // 2. Bad commands: NaN, and a 1 m jump out of the workspace. Rejected; the node goes on.
  const auto before = L.lastStatus();
  auto bad = pose(kBaseX + 0.015);
  bad.pose.position.y = std::nan("");
  cmd.publish(bad);
  cmd.publish(pose(kBaseX + 1.0));
  ASSERT_TRUE(waitFor([&] { return L.lastStatus().rejected_commands >= before.rejected_commands + 2; }, 5.0));
  ASSERT_TRUE(waitFor([&] { return L.lastStatus().step > before.step + 100; }, 5.0));
  EXPECT_EQ(L.lastStatus().state, "running");
  EXPECT_NEAR(L.tipX(), tip1, 1e-3);

  // 3. The deformation cloud, built once someone listens.
  auto s4 = nh.subscribe<sensor_msgs::PointCloud2>("tissue/deformation", 2, [&](const sensor_msgs::PointCloud2::ConstPtr& m) {
    std::lock_guard<std::mutex> lk(L.m);
    L.cloud = *m;
    L.have_cloud = true;
  });
  ASSERT_TRUE(waitFor([&] { std::lock_guard<std::mutex> lk(L.m); return L.have_cloud; }, 10.0));
  {
    std::lock_guard<std::mutex> lk(L.m);
    EXPECT_EQ(L.cloud.width * L.cloud.height, 9u * 5u * 5u);  // nodes of the 8x4x4 grid
    ASSERT_EQ(L.cloud.fields.size(), 8u);
    EXPECT_EQ(L.cloud.fields[3].name, "dx");
    EXPECT_EQ(L.cloud.fields[7].name, "eta");
    EXPECT_EQ(L.cloud.header.frame_id, "tissue");
    double umax = 0;
    bool finite = true;
    for (sensor_msgs::PointCloud2ConstIterator<float> it(L.cloud, "x"); it != it.end(); ++it) {
      for (int k = 0; k < 8; ++k) finite = finite && std::isfinite(it[k]);
      umax = std::max(umax, std::sqrt(double(it[3]) * it[3] + double(it[4]) * it[4] + double(it[5]) * it[5]));
    }
    EXPECT_TRUE(finite);
    EXPECT_GT(umax, 1e-8);
  }
  s4.shutdown();

  // 4. Surface and error markers: well formed, per-vertex colours, DELETEALL first.
  visualization_msgs::Marker surface;
  visualization_msgs::MarkerArray errors;
  bool have_surface = false, have_errors = false;
  auto s5 = nh.subscribe<visualization_msgs::Marker>("tissue/surface", 2, [&](const visualization_msgs::Marker::ConstPtr& m) {
    std::lock_guard<std::mutex> lk(L.m);
    surface = *m;
    have_surface = true;
  });
  auto s6 = nh.subscribe<visualization_msgs::MarkerArray>("tissue/error_markers", 2,
                                                          [&](const visualization_msgs::MarkerArray::ConstPtr& m) {
                                                            std::lock_guard<std::mutex> lk(L.m);
                                                            errors = *m;
                                                            have_errors = true;
                                                          });
  ASSERT_TRUE(waitFor([&] { std::lock_guard<std::mutex> lk(L.m); return have_surface && have_errors; }, 10.0));
  {
    std::lock_guard<std::mutex> lk(L.m);
    EXPECT_EQ(surface.type, visualization_msgs::Marker::TRIANGLE_LIST);
    EXPECT_EQ(surface.points.size() % 3, 0u);
    EXPECT_EQ(surface.points.size(), surface.colors.size());
    EXPECT_EQ(surface.points.size(), 6u * (2 * (8 * 4) * 2 + 2 * (4 * 4)));  // 2 triangles per boundary quad
    ASSERT_GE(errors.markers.size(), 2u);
    EXPECT_EQ(errors.markers[0].action, visualization_msgs::Marker::DELETEALL);
    EXPECT_EQ(errors.markers[1].ns, "level_0");
    EXPECT_EQ(errors.markers[1].type, visualization_msgs::Marker::CUBE_LIST);
    EXPECT_EQ(errors.markers[1].points.size(), 128u);
    EXPECT_EQ(errors.markers[1].points.size(), errors.markers[1].colors.size());
  }
  s5.shutdown();
  s6.shutdown();

  // 5. Diagnostics: the rejected commands above show as a warning or the node is OK again.
  bool have_diag = false;
  std::string level_name;
  std::map<std::string, std::string> values;
  auto s7 = nh.subscribe<diagnostic_msgs::DiagnosticArray>("/diagnostics", 10, [&](const diagnostic_msgs::DiagnosticArray::ConstPtr& m) {
    std::lock_guard<std::mutex> lk(L.m);
    for (const auto& d : m->status)
      if (d.name.find("simulation") != std::string::npos) {
        have_diag = true;
        level_name = d.message;
        for (const auto& kv : d.values) values[kv.key] = kv.value;
      }
  });
  ASSERT_TRUE(waitFor([&] { std::lock_guard<std::mutex> lk(L.m); return have_diag; }, 5.0));
  s7.shutdown();
  {
    // The pre-flight at start (#40): the scene's own motion timed on a copy (the default 2 s of
    // wall time), its verdict and figures kept in diagnostics.
    std::lock_guard<std::mutex> lk(L.m);
    const std::string verdict = values["preflight"];
    EXPECT_TRUE(verdict == "keeps real time" || verdict == "will not keep real time") << verdict;
    EXPECT_GT(std::stol(values["preflight_steps"]), 100);
    EXPECT_EQ(values["preflight_summary"].rfind("pre-flight: ", 0), 0u) << values["preflight_summary"];
    EXPECT_GT(std::stod(values["preflight_step_ms_max"]), 0.0);
  }

  // 6. Reset: the initial state again; the counters are lifetime counts and stay.
  const auto before_reset = L.lastStatus().rejected_commands;
  std_srvs::Trigger srv;
  ASSERT_TRUE(ros::service::waitForService("needle_sim/reset", 5000));
  ASSERT_TRUE(ros::service::call("needle_sim/reset", srv));
  EXPECT_TRUE(srv.response.success) << srv.response.message;
  ASSERT_TRUE(waitFor([&] { return L.lastStatus().step < 500; }, 5.0));
  EXPECT_EQ(L.lastStatus().rejected_commands, before_reset);
  ASSERT_TRUE(waitFor([&] { return std::abs(L.tipX() - tip0) < 1e-9; }, 5.0)) << L.tipX();
  EXPECT_EQ(L.lastStatus().insertion_states[0], "approaching");

  // 7. A planned trajectory: 2.5 mm in 1 s in free space (the tip stays 0.5 mm in front of
  //    the tissue), then held; a plan with a NaN waypoint is rejected whole.
  ros::Publisher plan = nh.advertise<needle_sim::NeedleTrajectory>("needle/command_trajectory", 10);
  ASSERT_TRUE(waitFor([&] { return plan.getNumSubscribers() > 0; }, 10.0));
  auto waypoint = [](double t, double x) {
    needle_sim::NeedleWaypoint w;
    w.time_from_start = ros::Duration(t);
    w.pose = pose(x).pose;
    return w;
  };
  needle_sim::NeedleTrajectory bad_plan;
  bad_plan.header.frame_id = "tissue";  // (an empty frame is refused: ~allow_empty_frame)
  bad_plan.waypoints = {waypoint(0.5, kBaseX + 0.001), waypoint(1.0, std::nan(""))};
  const auto rejected_before = L.lastStatus().rejected_commands;
  plan.publish(bad_plan);
  ASSERT_TRUE(waitFor([&] { return L.lastStatus().rejected_commands == rejected_before + 1; }, 5.0));
  needle_sim::NeedleTrajectory good_plan;
  good_plan.header.frame_id = "tissue";
  good_plan.waypoints = {waypoint(0.5, kBaseX + 0.00125), waypoint(1.0, kBaseX + 0.0025)};
  plan.publish(good_plan);
  clock.sleep(0.5);
  // Half-way (0.5 s of simulated time after the plan was sent, a few ms more on a loaded
  // machine): 1.25 mm of 2.5 (1.23 mm measured: the plan starts at the step that takes it).
  const double mid = L.tipX() - tip0;
  std::cout << "half-way through the plan: " << mid << " m\n";
  EXPECT_GT(mid, 0.0010);
  EXPECT_LT(mid, 0.00175);
  ASSERT_TRUE(waitFor([&] { return std::abs(L.tipX() - tip0 - 0.0025) < 5e-5; }, 5.0)) << L.tipX() - tip0;
  EXPECT_EQ(L.lastStatus().insertion_states[0], "approaching");
  EXPECT_EQ(L.lastStatus().rejected_commands, rejected_before + 1);

  // 8. Targets: set_target outside the tissue is refused (nothing changes); inside, the
  //    target is published as target/state (distance to the tip consistent with the path),
  //    target (PointStamped) and tf frames target/<name> and target.
  std::mutex tm;
  needle_sim::TargetState state;
  geometry_msgs::PointStamped primary;
  bool have_state = false, have_primary = false;
  auto s8 = nh.subscribe<needle_sim::TargetState>("target/state", 100, [&](const needle_sim::TargetState::ConstPtr& m) {
    std::lock_guard<std::mutex> lk(tm);
    state = *m;
    have_state = true;
  });
  auto s9 = nh.subscribe<geometry_msgs::PointStamped>("target", 10, [&](const geometry_msgs::PointStamped::ConstPtr& m) {
    std::lock_guard<std::mutex> lk(tm);
    primary = *m;
    have_primary = true;
  });
  ASSERT_TRUE(ros::service::waitForService("needle_sim/set_target", 5000));
  needle_sim::SetTarget set;
  set.request.name = "goal";
  set.request.point.x = 1.0, set.request.point.y = 1.0, set.request.point.z = 1.0;
  ASSERT_TRUE(ros::service::call("needle_sim/set_target", set));
  EXPECT_FALSE(set.response.success);
  EXPECT_NE(set.response.message.find("outside"), std::string::npos) << set.response.message;
  clock.sleep(0.3);
  {
    std::lock_guard<std::mutex> lk(tm);
    EXPECT_FALSE(have_state) << "no target exists yet";
  }
  set.request.point.x = 0.01, set.request.point.y = kY, set.request.point.z = kZ;
  ASSERT_TRUE(ros::service::call("needle_sim/set_target", set));
  EXPECT_TRUE(set.response.success) << set.response.message;
  ASSERT_TRUE(waitFor([&] { std::lock_guard<std::mutex> lk(tm); return have_state && have_primary; }, 5.0));
  {
    std::lock_guard<std::mutex> lk(tm);
    EXPECT_EQ(state.name, "goal");
    EXPECT_EQ(state.planned.x, 0.01);
    EXPECT_NEAR(state.position.x, 0.01, 1e-4);
    ASSERT_EQ(state.tip_distances.size(), 1u);  // one per needle, in scene order
    EXPECT_EQ(state.needles, std::vector<std::string>{"needle"});
    EXPECT_EQ(state.tip_distances[0], state.needle_tip_distance);
    EXPECT_NEAR(state.needle_tip_distance, 0.01 - L.tipX(), 2e-4);
    EXPECT_NEAR(primary.point.x, state.position.x, 1e-4);
    EXPECT_EQ(primary.header.frame_id, "tissue");
  }
  tf2_ros::Buffer buffer;
  tf2_ros::TransformListener listener(buffer);
  EXPECT_TRUE(buffer.canTransform("tissue", "target/goal", ros::Time(0), ros::Duration(3.0)));
  EXPECT_TRUE(buffer.canTransform("tissue", "target", ros::Time(0), ros::Duration(3.0)));
  // The needle tip's frame: at the centre line's last node, x axis along the needle (+x in
  // this scene), as the command poses; the path's orientations follow the same convention.
  ASSERT_TRUE(buffer.canTransform("tissue", "needle_tip", ros::Time(0), ros::Duration(3.0)));
  const geometry_msgs::TransformStamped tip = buffer.lookupTransform("tissue", "needle_tip", ros::Time(0));
  EXPECT_NEAR(tip.transform.translation.x, L.tipX(), 1e-4);
  EXPECT_NEAR(tip.transform.translation.y, kY, 1e-3);
  EXPECT_NEAR(tip.transform.translation.z, kZ, 1e-3);
  auto axisX = [](const geometry_msgs::Quaternion& q) {  // first column of the rotation
    return 1 - 2 * (q.y * q.y + q.z * q.z);
  };
  EXPECT_GT(axisX(tip.transform.rotation), 0.999);
  {
    std::lock_guard<std::mutex> lk(L.m);
    ASSERT_FALSE(L.path.poses.empty());
    EXPECT_GT(axisX(L.path.poses.front().pose.orientation), 0.999);
    EXPECT_GT(axisX(L.path.poses.back().pose.orientation), 0.999);
  }
  EXPECT_EQ(L.lastStatus().state, "running");

  // 9. predict: 12 mm more in 2 s (through the surface, towards the target), 2.5 s simulated
  //    on a copy at ~predict_dt = 10 ms; the live needle stays where it is while the live
  //    simulation goes on stepping. Bad plans are refused with the reason.
  ASSERT_TRUE(ros::service::waitForService("needle_sim/predict", 5000));
  needle_sim::PredictInsertion pr;
  pr.request.trajectory.header.frame_id = "tissue";
  pr.request.trajectory.waypoints = {waypoint(2.0, kBaseX + 0.0025 + 0.012)};
  pr.request.duration = 2.5;
  const double live_tip = L.tipX();
  const auto live_step = L.lastStatus().step;
  ASSERT_TRUE(ros::service::call("needle_sim/predict", pr));
  ASSERT_TRUE(pr.response.success) << pr.response.message;
  const auto& r = pr.response;
  EXPECT_EQ(r.steps, 250);
  ASSERT_EQ(r.time.size(), 51u);  // every 50 ms, now included
  EXPECT_EQ(r.time.front(), 0.0);
  EXPECT_NEAR(r.time.back(), 2.5, 1e-9);
  ASSERT_EQ(r.tip_position.size(), r.time.size());
  ASSERT_EQ(r.base_force.size(), r.time.size());
  ASSERT_EQ(r.target_position.size(), r.time.size());
  ASSERT_EQ(r.target_tip_distance.size(), r.time.size());
  EXPECT_NEAR(r.tip_position.front().x, live_tip, 1e-6);
  EXPECT_NEAR(r.tip_position.back().x - live_tip, 0.012, 3e-4);  // followed the plan
  EXPECT_LT(r.base_force.back().x, 0.0);                          // the tissue resists the insertion
  const double dx = r.target_position.back().x - r.tip_position.back().x,
               dy = r.target_position.back().y - r.tip_position.back().y,
               dz = r.target_position.back().z - r.tip_position.back().z;
  EXPECT_NEAR(r.final_target_tip_distance, std::sqrt(dx * dx + dy * dy + dz * dz), 1e-12);
  EXPECT_LT(r.final_target_tip_distance, 0.01 - live_tip);  // closer than now
  EXPECT_GT(r.target_position.back().x, 0.01);              // the target is pushed ahead
  EXPECT_GT(r.max_dofs, 0);
  EXPECT_GT(r.compute_time, 0.0);
  EXPECT_NEAR(L.tipX(), live_tip, 1e-9);  // the live needle did not move ...
  ASSERT_TRUE(waitFor([&] { return L.lastStatus().step > live_step + 10; }, 5.0));  // ... and it steps on
  EXPECT_EQ(L.lastStatus().insertion_states[0], "approaching");
  pr.request.trajectory.waypoints = {waypoint(0.5, kBaseX + 0.003), waypoint(1.0, std::nan(""))};
  ASSERT_TRUE(ros::service::call("needle_sim/predict", pr));
  EXPECT_FALSE(pr.response.success);
  EXPECT_NE(pr.response.message.find("waypoint 1"), std::string::npos) << pr.response.message;
  pr.request.trajectory.waypoints = {waypoint(1.0, kBaseX + 0.005)};
  pr.request.needle = "no_such_needle";
  ASSERT_TRUE(ros::service::call("needle_sim/predict", pr));
  EXPECT_FALSE(pr.response.success);
  EXPECT_NE(pr.response.message.find("no_such_needle"), std::string::npos) << pr.response.message;
  EXPECT_EQ(L.lastStatus().state, "running");
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "test_node");
  return RUN_ALL_TESTS();
}

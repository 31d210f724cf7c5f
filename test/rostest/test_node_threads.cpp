// The node's threads in one process, for the sanitizers (issue #39, item 5): SimulatorRos (the
// node's and the nodelet's class) made in this test's process on a real roscore, with two
// callback threads as needle_sim_node spins, on the adaptive phantom on the wall clock, while
// this process drives every thread the node has at once:
//   - the stepping thread, paced by itself, with mesh changes and factor refreshes built in
//     the background (phantom_insertion_adaptive);
//   - the output thread, with every output subscribed (status, wrench, the target's state,
//     the cloud, surface, markers and paths at the display rate);
//   - the target-error thread (a target added by ~set_target);
//   - the callback threads: base poses at 500 Hz from one thread, ~predict, ~set_target,
//     ~set_parameters (reconfigure) and ~reset from another, each while the others run;
//   - the predictions' callback thread;
// then the node destroyed while poses still arrive (a nodelet unloaded). Built in the regular
// build (rostest: node_threads.test), in the ASan build (scripts/sanitize.sh runs it through
// rostest) and against the ThreadSanitizer core (scripts/tsan.sh: test/tsan_ros builds the ROS
// layer with -fsanitize=thread and runs this binary beside a roscore of its own). A report of
// either sanitizer fails the run; the test itself checks that every thread did its work.
#include <gtest/gtest.h>
#include <dynamic_reconfigure/Reconfigure.h>
#include <diagnostic_msgs/DiagnosticArray.h>
#include <geometry_msgs/WrenchStamped.h>
#include <nav_msgs/Path.h>
#include <needle_sim/PredictInsertion.h>
#include <needle_sim/SetTarget.h>
#include <needle_sim/SimStatus.h>
#include <needle_sim/TargetState.h>
#include <ros/ros.h>
#include <sensor_msgs/PointCloud2.h>
#include <std_srvs/Trigger.h>
#include <visualization_msgs/Marker.h>
#include <visualization_msgs/MarkerArray.h>

#include <dirent.h>
#include <pthread.h>
#include <sched.h>

#include <atomic>
#include <cmath>
#include <fstream>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "needle_sim/ros/simulator_ros.hpp"
#include "wait_for.hpp"
#include "../unit/fifo_permitted.hpp"

namespace {

using needle_sim_test::waitFor;
const double kBaseX = -0.035, kY = 0.01, kZ = 0.01;  // phantom_insertion_8x4x4.yaml's base
const std::string kNs = "/threads_sim";

// What arrived, per output.
struct Received {
  std::mutex m;
  std::vector<needle_sim::SimStatus> statuses;
  std::atomic<int> wrench{0}, target{0}, target_bounds{0}, cloud{0}, surface{0}, error_markers{0}, target_markers{0},
      marker{0}, path{0};
  uint64_t lastStep() {
    std::lock_guard<std::mutex> lk(m);
    return statuses.empty() ? 0 : statuses.back().step;
  }
  size_t size() {
    std::lock_guard<std::mutex> lk(m);
    return statuses.size();
  }
  bool inserted() {
    std::lock_guard<std::mutex> lk(m);
    return !statuses.empty() && !statuses.back().insertion_states.empty() &&
           statuses.back().insertion_states[0] == "inserted";
  }
  uint32_t mostDofs() {
    std::lock_guard<std::mutex> lk(m);
    uint32_t d = 0;
    for (const auto& s : statuses) d = std::max(d, s.dofs);
    return d;
  }
};

template <class M>
ros::Subscriber count(ros::NodeHandle& nh, const std::string& topic, std::atomic<int>& n) {
  return nh.subscribe<M>(topic, 100, [&n](const typename M::ConstPtr&) { ++n; });
}

}  // namespace

TEST(NodeThreads, EveryThreadAtOnceThenTheNodeDestroyedWhileCommandsArrive) {
  ros::NodeHandle nh, pnh(kNs);
  pnh.setParam("scene", std::string(NEEDLE_SIM_SOURCE_DIR) + "/config/scenes/phantom_insertion_adaptive.yaml");
  pnh.setParam("command_source", std::string("topic"));
  pnh.setParam("target_error_period", 0.05);
  pnh.setParam("display_rate", 50.0);
  // The predictions' thread is SCHED_IDLE: under a sanitizer, with the stepping thread behind,
  // a short prediction may wait for a core (the budget is for a prediction's own length).
  pnh.setParam("predict_max_wall", 60.0);
  // The online estimate's thread too (node_assimilation.hpp): measured wrenches arrive with the
  // poses, its refits run beside the steps and are cancelled by the reset and the node's end.
  pnh.setParam("assimilation/keys", std::string("interaction.cutting_force"));
  pnh.setParam("assimilation/wrench_noise", 0.0005);
  pnh.setParam("assimilation/every", 0.2);
  auto sim = std::make_unique<needle_sim::SimulatorRos>(nh, pnh);
  ros::AsyncSpinner spinner(2);  // needle_sim_node's MultiThreadedSpinner(2)
  spinner.start();

  Received rx;
  std::vector<ros::Subscriber> subs;
  subs.push_back(pnh.subscribe<needle_sim::SimStatus>("status", 10000, [&](const needle_sim::SimStatus::ConstPtr& s) {
    std::lock_guard<std::mutex> lk(rx.m);
    rx.statuses.push_back(*s);
  }));
  subs.push_back(pnh.subscribe<needle_sim::TargetState>("target/state", 1000, [&](const needle_sim::TargetState::ConstPtr& t) {
    ++rx.target;
    if (std::isfinite(t->displacement_error_bound)) ++rx.target_bounds;
  }));
  subs.push_back(count<geometry_msgs::WrenchStamped>(pnh, "needle/wrench", rx.wrench));
  subs.push_back(count<sensor_msgs::PointCloud2>(pnh, "tissue/deformation", rx.cloud));
  subs.push_back(count<visualization_msgs::Marker>(pnh, "tissue/surface", rx.surface));
  subs.push_back(count<visualization_msgs::MarkerArray>(pnh, "tissue/error_markers", rx.error_markers));
  subs.push_back(count<visualization_msgs::MarkerArray>(pnh, "target/markers", rx.target_markers));
  subs.push_back(count<visualization_msgs::Marker>(pnh, "needle/marker", rx.marker));
  subs.push_back(count<nav_msgs::Path>(pnh, "needle/path", rx.path));
  ASSERT_TRUE(waitFor([&] { return rx.lastStep() > 10; }, 60.0)) << "the node does not step";

  // Base poses at 500 Hz: in along the axis at 10 mm/s, from the start again after a reset.
  ros::Publisher poses = pnh.advertise<geometry_msgs::PoseStamped>("needle/command_pose", 100);
  ros::Publisher measured = pnh.advertise<geometry_msgs::WrenchStamped>("needle/measured_wrench", 100);
  std::atomic<bool> publishing{true};
  std::atomic<double> pose_t0{ros::WallTime::now().toSec()};
  std::atomic<int> sent{0};
  std::thread commander([&] {
    ros::WallRate rate(500);
    while (publishing) {
      const double t = ros::WallTime::now().toSec() - pose_t0;
      poses.publish(needle_sim_test::basePose(kBaseX + 0.010 * std::min(t, 3.0), kY, kZ));
      if (sent % 5 == 0) {  // a force sensor at 100 Hz
        geometry_msgs::WrenchStamped w;
        w.header.stamp = ros::Time::now();
        w.header.frame_id = "needle_base";
        w.wrench.force.x = -0.02;
        measured.publish(w);
      }
      ++sent;
      rate.sleep();
    }
  });
  struct Join {  // on any return: the commander stopped before what it uses goes
    std::atomic<bool>& flag;
    std::thread& t;
    ~Join() {
      flag = false;
      if (t.joinable()) t.join();
    }
  } join_commander{publishing, commander};

  // From a second thread, as a planner and an operator would, while the poses arrive.
  ASSERT_TRUE(ros::service::waitForService(kNs + "/predict", 10000));
  needle_sim::SetTarget st;
  st.request.name = "inside";
  st.request.point.x = 0.01, st.request.point.y = kY, st.request.point.z = kZ;
  ASSERT_TRUE(ros::service::call(kNs + "/set_target", st));
  EXPECT_TRUE(st.response.success) << st.response.message;

  std::atomic<int> predictions{0};
  std::thread planner([&] {
    for (int k = 0; k < 3; ++k) {
      needle_sim::PredictInsertion pr;
      pr.request.trajectory.header.frame_id = "tissue";
      // To 15 mm in over 0.8 s, the first 0.3 s of it predicted: the live base is somewhere
      // between the start and the commands' 30 mm (under ASan the stepping falls far behind
      // the commands, on a fast machine it keeps up), at most 15 mm away: under 19 mm/s,
      // inside both limits whenever the prediction runs (an aim 9 mm in, 0.3 s away, was
      // faster than the 40 mm/s set below once the base had passed 21 mm).
      needle_sim::NeedleWaypoint w;
      w.time_from_start = ros::Duration(0.8);
      w.pose.position.x = kBaseX + 0.015, w.pose.position.y = kY, w.pose.position.z = kZ;
      w.pose.orientation.w = 1;
      pr.request.trajectory.waypoints = {w};
      pr.request.duration = 0.3;
      if (ros::service::call(kNs + "/predict", pr) && pr.response.success) ++predictions;
      else ADD_FAILURE() << "predict: " << pr.response.message;
    }
  });
  dynamic_reconfigure::Reconfigure rc;
  dynamic_reconfigure::DoubleParameter speed;
  speed.name = "max_speed", speed.value = 0.04;
  rc.request.config.doubles = {speed};
  EXPECT_TRUE(ros::service::call(kNs + "/set_parameters", rc));
  planner.join();
  EXPECT_EQ(predictions.load(), 3);

  // The insertion goes on until the adaptive mesh has changed, then a reset while the poses
  // arrive, and the run goes on from the start.
  const uint32_t start_dofs = [&] {
    std::lock_guard<std::mutex> lk(rx.m);
    return rx.statuses.front().dofs;
  }();
  EXPECT_TRUE(waitFor([&] { return rx.mostDofs() > start_dofs; }, 120.0)) << "no mesh change";
  EXPECT_TRUE(waitFor([&] { return rx.inserted(); }, 120.0)) << "the needle did not puncture";
  EXPECT_TRUE(waitFor([&] { return sent >= 1000; }, 120.0));  // 2 s of poses at least
  std_srvs::Trigger reset;
  ASSERT_TRUE(ros::service::call(kNs + "/reset", reset));
  EXPECT_TRUE(reset.response.success) << reset.response.message;
  pose_t0 = ros::WallTime::now().toSec();
  const size_t after_reset = rx.size();
  EXPECT_TRUE(waitFor([&] { return rx.size() > after_reset + 500; }, 120.0)) << "too few steps after the reset";

  // Every thread did its work.
  EXPECT_GT(rx.wrench.load(), 0);
  EXPECT_GT(rx.target.load(), 0);
  EXPECT_GT(rx.target_bounds.load(), 0) << "no error bound from the target-error thread";
  EXPECT_GT(rx.cloud.load(), 0);
  EXPECT_GT(rx.surface.load(), 0);
  EXPECT_GT(rx.error_markers.load(), 0);
  EXPECT_GT(rx.target_markers.load(), 0);
  EXPECT_GT(rx.marker.load(), 0);
  EXPECT_GT(rx.path.load(), 0);
  {
    std::lock_guard<std::mutex> lk(rx.m);
    for (const auto& s : rx.statuses) ASSERT_NE(s.state, "failed") << "step " << s.step;
    EXPECT_EQ(rx.statuses.back().state, "running");
  }

  // The node goes while poses still arrive and its callbacks run (a nodelet unloaded).
  sim.reset();
  publishing = false;
  commander.join();
  spinner.stop();
  std::cout << sent.load() << " poses sent, " << rx.size() << " steps, " << rx.cloud.load() << " clouds, "
            << rx.target_bounds.load() << " target states with a bound\n";
}

// ~target_error_duty: estimates asked for at every step (a period of one step) would run back
// to back; at a duty of a quarter their wall time stays within a quarter of the time that
// passed (plus the one under way). Read from the node's diagnostics. Ignoring the duty, the
// share is about one.
TEST(NodeThreads, TheTargetErrorEstimatesKeepToTheirDuty) {
  const std::string ns = "/duty_sim";
  ros::NodeHandle nh, pnh(ns);
  pnh.setParam("scene", std::string(NEEDLE_SIM_SOURCE_DIR) + "/config/scenes/phantom_insertion_8x4x4.yaml");
  pnh.setParam("target_error_period", 0.001);
  pnh.setParam("target_error_duty", 0.25);
  pnh.setParam("preflight_wall", 0.0);
  std::mutex m;
  std::map<std::string, std::string> diag;
  ros::Subscriber ds = nh.subscribe<diagnostic_msgs::DiagnosticArray>(
      "/diagnostics", 100, [&](const diagnostic_msgs::DiagnosticArray::ConstPtr& a) {
        for (const auto& st : a->status)
          if (st.name.find("simulation") != std::string::npos) {
            std::lock_guard<std::mutex> lk(m);
            for (const auto& kv : st.values) diag[kv.key] = kv.value;
          }
      });
  auto sim = std::make_unique<needle_sim::SimulatorRos>(nh, pnh);
  ros::AsyncSpinner spinner(2);
  spinner.start();
  ASSERT_TRUE(ros::service::waitForService(ns + "/set_target", 10000));
  const double t0 = ros::WallTime::now().toSec();
  needle_sim::SetTarget st;
  st.request.name = "inside";
  st.request.point.x = 0.01, st.request.point.y = kY, st.request.point.z = kZ;
  ASSERT_TRUE(ros::service::call(ns + "/set_target", st));
  ASSERT_TRUE(st.response.success) << st.response.message;
  ros::WallDuration(6.0).sleep();
  auto value = [&](const std::string& k) {
    std::lock_guard<std::mutex> lk(m);
    auto it = diag.find(k);
    return it == diag.end() ? std::nan("") : std::stod(it->second);
  };
  ASSERT_TRUE(waitFor([&] { return value("target_error_estimates") >= 5; }, 10.0)) << "too few estimates";
  const double elapsed = ros::WallTime::now().toSec() - t0;
  const double total = value("target_error_wall_s_total"), longest = value("target_error_wall_s_max");
  std::cout << value("target_error_estimates") << " estimates, " << total << " s of " << elapsed
            << " s of wall time, the longest " << longest << " s\n";
  EXPECT_LE(total, 0.25 * elapsed + longest);
  spinner.stop();
  sim.reset();
}

// ~realtime_priority: by default (-1) the stepping thread takes SCHED_FIFO 10 where the process
// may, and says so in the diagnostics (stepping_thread); 0 keeps the default scheduler. The
// threads' policies are read from the kernel (sched_getscheduler of each thread named ns_step).
namespace {

// (policy, priority) of this process's thread with this name; (-1, -1) if there is none.
std::pair<int, int> threadPolicy(const std::string& name) {
  DIR* d = opendir("/proc/self/task");
  std::pair<int, int> r{-1, -1};
  if (!d) return r;
  while (dirent* e = readdir(d)) {
    if (e->d_name[0] == '.') continue;
    std::ifstream comm(std::string("/proc/self/task/") + e->d_name + "/comm");
    std::string c;
    std::getline(comm, c);
    if (c != name) continue;
    const pid_t tid = static_cast<pid_t>(std::stol(e->d_name));
    sched_param p{};
    r.first = sched_getscheduler(tid);
    r.second = sched_getparam(tid, &p) == 0 ? p.sched_priority : -1;
  }
  closedir(d);
  return r;
}
}  // namespace

TEST(NodeThreads, TheSteppingThreadTakesRealTimePriorityWhereItMay) {
  const bool permitted = needle_sim_test::fifoPermitted();
  for (const int asked : {-1, 0}) {
    const std::string ns = "/rt_sim";
    ros::NodeHandle nh, pnh(ns);
    pnh.setParam("scene", std::string(NEEDLE_SIM_SOURCE_DIR) + "/config/scenes/phantom_insertion_8x4x4.yaml");
    pnh.setParam("preflight_wall", 0.0);
    pnh.setParam("realtime_priority", asked);
    std::mutex m;
    std::string said;
    ros::Subscriber ds = nh.subscribe<diagnostic_msgs::DiagnosticArray>(
        "/diagnostics", 100, [&](const diagnostic_msgs::DiagnosticArray::ConstPtr& a) {
          for (const auto& st : a->status)
            for (const auto& kv : st.values)
              if (kv.key == "stepping_thread") {
                std::lock_guard<std::mutex> lk(m);
                said = kv.value;
              }
        });
    auto sim = std::make_unique<needle_sim::SimulatorRos>(nh, pnh);
    ros::AsyncSpinner spinner(2);
    spinner.start();
    ASSERT_TRUE(waitFor([&] { return threadPolicy("ns_step").first >= 0; }, 10.0)) << "no thread named ns_step";
    const bool fifo = asked != 0 && permitted;
    const std::string expected = fifo ? "SCHED_FIFO 10" : "default scheduler";
    waitFor([&] {
      std::lock_guard<std::mutex> lk(m);
      return said == expected;
    }, 10.0);
    const auto policy = threadPolicy("ns_step");
    EXPECT_EQ(policy.first, fifo ? SCHED_FIFO : SCHED_OTHER) << "~realtime_priority " << asked;
    if (fifo) {
      EXPECT_EQ(policy.second, 10);
    }
    {
      std::lock_guard<std::mutex> lk(m);
      EXPECT_EQ(said, expected) << "~realtime_priority " << asked;
    }
    spinner.stop();
    sim.reset();
    pnh.deleteParam("realtime_priority");
  }
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "test_node_threads");
  return RUN_ALL_TESTS();
}

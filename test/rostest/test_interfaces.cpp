// rostest (interfaces.test): the node's standard interfaces, under a clock owned by the test.
//  - tf tree: ~parent_frame world -> tissue (static, ~tissue_pose), tissue -> needle_base;
//    the wrench is stamped in needle_base.
//  - trajectory_msgs/MultiDOFJointTrajectory is followed like the equivalent
//    needle_sim/NeedleTrajectory: the same tip positions, step by step, to 1e-9 m.
//  - dynamic_reconfigure: a lower ~max_speed is enforced at once; a set that fails the
//    checks is refused whole.
//  - the ~insert action: a goal reaches its target with feedback (axial_force = force.x,
//    negative while the needle cuts: the wrench's sign); a preempted goal holds the
//    needle; an unknown target and a speed above the limit are rejected.
#include <actionlib/client/simple_action_client.h>
#include <dynamic_reconfigure/client.h>
#include <gtest/gtest.h>
#include <needle_sim/InsertNeedleAction.h>
#include <needle_sim/LimitsConfig.h>
#include <ros/ros.h>
#include <tf2_ros/buffer.h>
#include <tf2_ros/transform_listener.h>

#include <atomic>
#include <cmath>
#include <map>
#include <mutex>
#include <thread>

#include <geometry_msgs/PoseStamped.h>
#include <geometry_msgs/WrenchStamped.h>
#include <needle_sim/NeedleTrajectory.h>
#include <needle_sim/SetTarget.h>
#include <needle_sim/SimStatus.h>
#include <needle_sim/TargetState.h>
#include <std_srvs/Trigger.h>
#include <trajectory_msgs/MultiDOFJointTrajectory.h>

#include "sim_clock.hpp"
#include "wait_for.hpp"

namespace {

using needle_sim_test::waitFor;
const double kBaseX = -0.035, kY = 0.01, kZ = 0.01;  // phantom_insertion_8x4x4.yaml

struct Status {
  std::mutex m;
  needle_sim::SimStatus last;
  std::map<uint64_t, geometry_msgs::Point> tips;  // by step, while recording
  bool recording = false;
  std::string wrench_frame;
  void on(const needle_sim::SimStatus::ConstPtr& s) {
    std::lock_guard<std::mutex> lk(m);
    last = *s;
    if (recording && !s->tips.empty()) tips[s->step] = s->tips[0];
  }
  needle_sim::SimStatus get() {
    std::lock_guard<std::mutex> lk(m);
    return last;
  }
  uint64_t count(const std::string& rule) {
    uint64_t n = 0;
    needle_sim_test::guardCount(get(), rule, n);
    return n;
  }
};

bool simWait(Status& st, double d) {
  const double t0 = st.get().sim_time;
  return waitFor([&] { return st.get().sim_time >= t0 + d; }, 4 * d + 5);
}

geometry_msgs::Pose basePose(double x) { return needle_sim_test::basePose(x, kY, kZ).pose; }

bool reset() {
  std_srvs::Trigger t;
  return ros::service::call("needle_sim/reset", t) && t.response.success;
}

// A reset, and the first status of the new run seen (so that waits on its simulated time
// do not start from a status of the run before).
bool resetAndWait(Status& st) {
  const uint64_t before = st.get().step;
  return reset() && waitFor([&] { return st.get().step < before && st.get().step > 0; }, 10.0);
}

}  // namespace

TEST(Interfaces, TfTreeTrajectoriesReconfigureAndTheInsertAction) {
  ros::NodeHandle nh("needle_sim");
  needle_sim_test::SimClock clock(nh);
  Status st;
  auto s1 = nh.subscribe<needle_sim::SimStatus>("status", 5000, [&](const needle_sim::SimStatus::ConstPtr& s) { st.on(s); });
  auto s2 = nh.subscribe<geometry_msgs::WrenchStamped>("needle/wrench", 10, [&](const geometry_msgs::WrenchStamped::ConstPtr& w) {
    std::lock_guard<std::mutex> lk(st.m);
    st.wrench_frame = w->header.frame_id;
  });
  ros::Publisher plan_pub = nh.advertise<needle_sim::NeedleTrajectory>("needle/command_trajectory", 10);
  ros::Publisher multi_pub = nh.advertise<trajectory_msgs::MultiDOFJointTrajectory>("needle/multi_dof_trajectory", 10);
  ros::Publisher cmd = nh.advertise<geometry_msgs::PoseStamped>("needle/command_pose", 100);
  ros::AsyncSpinner spinner(3);
  spinner.start();
  ASSERT_TRUE(waitFor([&] { return st.get().step > 20; }, 30.0));
  ASSERT_TRUE(waitFor([&] { return plan_pub.getNumSubscribers() > 0 && multi_pub.getNumSubscribers() > 0; }, 10.0));
  ASSERT_TRUE(ros::service::waitForService("needle_sim/reset", 5000));

  // 1. The tf tree attaches to a robot's: world -> tissue -> needle_base, needle_tip.
  tf2_ros::Buffer buffer;
  tf2_ros::TransformListener listener(buffer);
  ASSERT_TRUE(buffer.canTransform("world", "needle_base", ros::Time(0), ros::Duration(5.0)));
  const auto wt = buffer.lookupTransform("world", "tissue", ros::Time(0));
  EXPECT_DOUBLE_EQ(wt.transform.translation.x, 0.1);
  const auto base = buffer.lookupTransform("world", "needle_base", ros::Time(0));
  EXPECT_NEAR(base.transform.translation.x, 0.1 + kBaseX, 1e-9);
  EXPECT_TRUE(buffer.canTransform("needle_base", "needle_tip", ros::Time(0), ros::Duration(2.0)));
  {
    std::lock_guard<std::mutex> lk(st.m);
    EXPECT_EQ(st.wrench_frame, "needle_base");
  }

  // 2. The same plan as a NeedleTrajectory and as a MultiDOFJointTrajectory, each from a
  //    reset taken while the clock stands still (the plan is then taken before step 1).
  auto run = [&](const std::function<void()>& send) {
    clock.paused = true;
    ros::WallDuration(0.2).sleep();
    EXPECT_TRUE(reset());
    {
      std::lock_guard<std::mutex> lk(st.m);
      st.tips.clear();
      st.recording = true;
    }
    send();
    ros::WallDuration(0.5).sleep();  // the node has it queued
    clock.paused = false;
    waitFor([&] {
      std::lock_guard<std::mutex> lk(st.m);
      return st.tips.size() >= 600 && st.tips.count(600);
    }, 20.0);
    std::lock_guard<std::mutex> lk(st.m);
    st.recording = false;
    return st.tips;
  };
  // The tip starts 3 mm before the surface: 3 mm in 0.5 s, then 0.5 mm more in 0.25 s
  // (it touches the surface and indents it).
  const double t1 = 0.5, t2 = 0.75, x1 = kBaseX + 0.003, x2 = kBaseX + 0.0035;
  const auto a = run([&] {
    needle_sim::NeedleTrajectory m;
    m.header.frame_id = "tissue";
    for (auto [t, x] : {std::pair{t1, x1}, std::pair{t2, x2}}) {
      needle_sim::NeedleWaypoint w;
      w.time_from_start = ros::Duration(t);
      w.pose = basePose(x);
      m.waypoints.push_back(w);
    }
    plan_pub.publish(m);
  });
  const auto b = run([&] {
    trajectory_msgs::MultiDOFJointTrajectory m;
    m.header.frame_id = "world";  // the same poses, given in the parent frame
    m.joint_names = {"needle"};
    for (auto [t, x] : {std::pair{t1, x1}, std::pair{t2, x2}}) {
      trajectory_msgs::MultiDOFJointTrajectoryPoint p;
      geometry_msgs::Transform tr;
      tr.translation.x = x + 0.1;
      tr.translation.y = kY;
      tr.translation.z = kZ;
      tr.rotation.w = 1;
      p.transforms.push_back(tr);
      p.time_from_start = ros::Duration(t);
      m.points.push_back(p);
    }
    multi_pub.publish(m);
  });
  ASSERT_GE(a.size(), 600u);
  ASSERT_GE(b.size(), 600u);
  double diff = 0;
  int compared = 0;
  for (const auto& [step, p] : a) {
    auto it = b.find(step);
    if (it == b.end() || step > 600) continue;
    diff = std::max(diff, std::hypot(p.x - it->second.x, p.y - it->second.y, p.z - it->second.z));
    ++compared;
  }
  EXPECT_GT(compared, 500);
  EXPECT_LT(diff, 1e-9);
  EXPECT_GT(a.at(600).x + 0.003, 0.0029) << "the plan was followed";

  // 3. dynamic_reconfigure: max_speed 5 mm/s, enforced on the next command.
  dynamic_reconfigure::Client<needle_sim::LimitsConfig> client("/needle_sim");
  needle_sim::LimitsConfig cfg;
  ASSERT_TRUE(client.getCurrentConfiguration(cfg, ros::Duration(5.0)));
  EXPECT_DOUBLE_EQ(cfg.max_speed, 0.05);
  cfg.max_speed = 0.005;
  ASSERT_TRUE(client.setConfiguration(cfg));
  ASSERT_TRUE(resetAndWait(st));
  const uint64_t limited = st.count("linear_speed");
  auto p = needle_sim_test::basePose(kBaseX - 0.005, kY, kZ);
  cmd.publish(p);
  ASSERT_TRUE(waitFor([&] { return st.count("linear_speed") == limited + 1; }, 5.0));
  ASSERT_TRUE(simWait(st, 0.5));
  const double moved = kBaseX - st.get().bases[0].position.x;
  EXPECT_GT(moved, 0.0015);
  EXPECT_LT(moved, 0.003) << "at 5 mm/s, 0.5 s";
  //    A set that fails the checks (the inserted limit above the general one) is refused whole.
  needle_sim::LimitsConfig bad = cfg;
  bad.max_speed = 0.02;
  bad.max_angular_speed_inserted = 5.0;
  client.setConfiguration(bad);
  ros::WallDuration(0.5).sleep();
  ASSERT_TRUE(client.getCurrentConfiguration(cfg, ros::Duration(5.0)));
  EXPECT_DOUBLE_EQ(cfg.max_speed, 0.005);
  EXPECT_DOUBLE_EQ(cfg.max_angular_speed_inserted, 0.1);
  cfg.max_speed = 0.05;
  ASSERT_TRUE(client.setConfiguration(cfg));

  // 4. The ~insert action.
  actionlib::SimpleActionClient<needle_sim::InsertNeedleAction> ac(nh, "insert", false);
  ASSERT_TRUE(ac.waitForServer(ros::Duration(5.0)));
  ASSERT_TRUE(resetAndWait(st));
  needle_sim::SetTarget set;
  set.request.name = "goal";
  set.request.point.x = 0.012, set.request.point.y = kY, set.request.point.z = kZ;
  ASSERT_TRUE(ros::service::call("needle_sim/set_target", set));
  ASSERT_TRUE(set.response.success) << set.response.message;
  //    The target's error bound (goal-oriented estimate, every ~target_error_period of
  //    simulated time, off the stepping thread) is published with its state.
  std::mutex tm;
  needle_sim::TargetState ts;
  auto s3 = nh.subscribe<needle_sim::TargetState>("target/state", 100, [&](const needle_sim::TargetState::ConstPtr& m) {
    std::lock_guard<std::mutex> lk(tm);
    ts = *m;
  });
  ASSERT_TRUE(waitFor([&] {
    std::lock_guard<std::mutex> lk(tm);
    return std::isfinite(ts.displacement_error_bound);
  }, 10.0)) << "no error bound on ~target/state";
  {
    std::lock_guard<std::mutex> lk(tm);
    EXPECT_GE(ts.displacement_error_bound, 0.0);
    EXPECT_TRUE(std::isfinite(ts.displacement_error.x) && std::isfinite(ts.displacement_error.z));
    EXPECT_LE(std::abs(ts.displacement_error.x), ts.displacement_error_bound);
  }
  // The estimate's own step, refreshed every ~target_error_period (0.2 s: 200 steps).
  int64_t first_error_step;
  {
    std::lock_guard<std::mutex> lk(tm);
    first_error_step = ts.error_step;
  }
  EXPECT_GE(first_error_step, 0);
  EXPECT_TRUE(waitFor([&] {
    std::lock_guard<std::mutex> lk(tm);
    return ts.error_step >= first_error_step + 150;
  }, 20.0)) << "the estimate's step did not advance from " << first_error_step;
  //    4a. To 3 mm before the target at 10 mm/s: 12 mm of travel in 1.2 s.
  std::atomic<int> feedback{0};
  std::atomic<double> last_distance{NAN}, last_axial{NAN};
  std::atomic<int> axial_not_force_x{0};
  needle_sim::InsertNeedleGoal goal;
  goal.target = "goal";
  goal.speed = 0.01;
  goal.stop_distance = 0.003;
  ac.sendGoal(goal, {}, {}, [&](const needle_sim::InsertNeedleFeedbackConstPtr& f) {
    ++feedback;
    last_distance = f->distance;
    last_axial = f->axial_force;
    axial_not_force_x += f->axial_force != f->force.x;
  });
  ASSERT_TRUE(ac.waitForResult(ros::Duration(20.0)));
  EXPECT_EQ(ac.getState(), actionlib::SimpleClientGoalState::SUCCEEDED) << ac.getState().getText();
  const auto r = *ac.getResult();
  EXPECT_GT(feedback.load(), 8);  // 10 Hz of simulated time over 1.2 s
  // The axial force (observables.hpp): the x of the force on the holder in <needle>_base, the
  // wrench's sign, negative while the needle cuts its way in.
  EXPECT_EQ(axial_not_force_x.load(), 0);
  EXPECT_LT(last_axial.load(), -0.005);
  EXPECT_NEAR(r.inserted, 0.012, 1e-6);
  EXPECT_GT(r.final_distance, 0.002);  // the target is pushed ahead of the tip ...
  EXPECT_LT(r.final_distance, 0.006);  // ... by a few millimetres at most
  EXPECT_EQ(r.state, "inserted");
  EXPECT_TRUE(std::isfinite(r.error_bound) && r.error_bound >= 0) << r.error_bound;
  //    4b. Preempted half-way: the needle holds where it is.
  ASSERT_TRUE(resetAndWait(st));
  goal = needle_sim::InsertNeedleGoal();
  goal.point.x = 0.02, goal.point.y = kY, goal.point.z = kZ;
  goal.depth = 0.01;
  goal.speed = 0.005;
  ac.sendGoal(goal);
  ASSERT_TRUE(waitFor([&] { return ac.getState() == actionlib::SimpleClientGoalState::ACTIVE; }, 5.0));
  ASSERT_TRUE(simWait(st, 0.5));
  ac.cancelGoal();
  ASSERT_TRUE(ac.waitForResult(ros::Duration(5.0)));
  EXPECT_EQ(ac.getState(), actionlib::SimpleClientGoalState::PREEMPTED);
  ASSERT_TRUE(simWait(st, 0.05));
  const double held = st.get().bases[0].position.x;
  EXPECT_GT(held - kBaseX, 0.001);
  EXPECT_LT(held - kBaseX, 0.004);
  ASSERT_TRUE(simWait(st, 0.5));
  EXPECT_NEAR(st.get().bases[0].position.x, held, 1e-12) << "the needle holds";
  //    4c. Rejected goals.
  goal = needle_sim::InsertNeedleGoal();
  goal.target = "no_such_target";
  ac.sendGoal(goal);
  ASSERT_TRUE(ac.waitForResult(ros::Duration(5.0)));
  EXPECT_EQ(ac.getState(), actionlib::SimpleClientGoalState::REJECTED);
  EXPECT_NE(ac.getState().getText().find("no_such_target"), std::string::npos) << ac.getState().getText();
  goal.target = "goal";
  goal.speed = 1.0;  // above ~max_speed
  ac.sendGoal(goal);
  ASSERT_TRUE(ac.waitForResult(ros::Duration(5.0)));
  EXPECT_EQ(ac.getState(), actionlib::SimpleClientGoalState::REJECTED);
  EXPECT_EQ(st.get().state, "running");
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "test_interfaces");
  return RUN_ALL_TESTS();
}

// rostest (guard_safety.test): issue #39, the holes of the node's command guard, on the real
// node under a clock owned by the test (1 ms of /clock per 2 ms of wall time), phantom
// 8x4x4, ~max_speed_ceiling 0.09 m/s, a second process (second_commander.py) that can
// command the same needle.
//  1. dynamic_reconfigure refuses, whole: max_speed 1e9, inf, NaN, -1, 0 and above the
//     ceiling come back as the old value (what `dynparam set` gets), an ERROR names the
//     rule or the ceiling, diagnostics count them; a valid set is taken.
//  2. One source per needle: while this process commands the needle, the second process's
//     commands are rejected under rule owner, with a warning naming both caller ids; silent
//     for ~owner_timeout, it gives the needle up; an ~insert goal holds the needle.
//  3. The tip watched: after the axis is turned 0.2 rad inside the tissue, ~predict shows
//     the tip's snap-back on withdrawal; the withdrawal warns (tip_speed) and diagnostics
//     carry the same speed as the tips of ~status, step to step; a straight insertion does
//     not warn.
//  4. ~predict's dt above ~predict_max_dt is refused, naming it.
#include <actionlib/client/simple_action_client.h>
#include <diagnostic_msgs/DiagnosticArray.h>
#include <dynamic_reconfigure/Reconfigure.h>
#include <gtest/gtest.h>
#include <needle_sim/InsertNeedleAction.h>
#include <needle_sim/PredictInsertion.h>
#include <needle_sim/SimStatus.h>
#include <ros/ros.h>
#include <rosgraph_msgs/Log.h>
#include <std_msgs/Bool.h>
#include <std_srvs/Trigger.h>

#include <Eigen/Geometry>
#include <sched.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <limits>
#include <sstream>
#include <map>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include <geometry_msgs/PoseStamped.h>

#include "sim_clock.hpp"
#include "status_recorder.hpp"
#include "wait_for.hpp"

namespace {

using needle_sim_test::waitFor;
const double kBaseX = -0.035, kY = 0.01, kZ = 0.01;  // phantom_insertion_8x4x4.yaml (tip 3 mm before x = 0)

struct Sample {
  uint64_t step;
  double t;
  Eigen::Vector3d base, tip;
};

// What the node says: ~status every step, /diagnostics, its log.
struct Node : needle_sim_test::StatusRecorder<Sample> {
  std::map<std::string, diagnostic_msgs::DiagnosticStatus> diag;  // latest per status name
  std::vector<diagnostic_msgs::DiagnosticStatus> tip_reports;      // every tip_speed report
  std::vector<rosgraph_msgs::Log> log;
  void onStatus(const needle_sim::SimStatus::ConstPtr& s) {
    std::lock_guard<std::mutex> lk(m);
    last = *s;
    if (s->bases.empty()) return;
    const auto& b = s->bases[0].position;
    const auto& p = s->tips[0];
    samples.push_back({s->step, s->sim_time, Eigen::Vector3d(b.x, b.y, b.z), Eigen::Vector3d(p.x, p.y, p.z)});
  }
  void onDiag(const diagnostic_msgs::DiagnosticArray::ConstPtr& a) {
    std::lock_guard<std::mutex> lk(m);
    for (const auto& s : a->status) {
      diag[s.name] = s;
      if (s.name.find("tip_speed") != std::string::npos) tip_reports.push_back(s);
    }
  }
  void onLog(const rosgraph_msgs::Log::ConstPtr& l) {
    std::lock_guard<std::mutex> lk(m);
    if (l->name == "/needle_sim") log.push_back(*l);
  }
  // Log messages of the node at `level` since entry k that contain every one of `words`.
  int logged(size_t k, uint8_t level, const std::vector<std::string>& words) {
    std::lock_guard<std::mutex> lk(m);
    int n = 0;
    for (size_t i = k; i < log.size(); ++i) {
      bool all = log[i].level == level;
      for (const auto& w : words) all = all && log[i].msg.find(w) != std::string::npos;
      n += all;
    }
    return n;
  }
  size_t logSize() {
    std::lock_guard<std::mutex> lk(m);
    return log.size();
  }
  // A key of the latest diagnostics status whose name contains `name` ("" if none).
  std::string diagValue(const std::string& name, const std::string& key, uint8_t* level = nullptr) {
    std::lock_guard<std::mutex> lk(m);
    for (const auto& [n, s] : diag)
      if (n.find(name) != std::string::npos) {
        if (level) *level = s.level;
        for (const auto& kv : s.values)
          if (kv.key == key) return kv.value;
      }
    return "";
  }
};

geometry_msgs::PoseStamped pose(double x, const Eigen::Quaterniond& q = Eigen::Quaterniond::Identity()) {
  return needle_sim_test::basePose(x, kY, kZ, q.w(), q.x(), q.y(), q.z());
}

using needle_sim_test::simWait;

bool resetAndWait(Node& n) {
  std_srvs::Trigger t;
  // The count must be far enough from 0 for the restart to be seen (a reset just after
  // another, as one test after another, would restart from a count the poll may miss).
  if (!waitFor([&] { return n.status().step >= 50; }, 30.0)) return false;
  const uint64_t before = n.status().step;
  return ros::service::call("needle_sim/reset", t) && t.response.success &&
         waitFor([&] { return n.status().step < before && n.status().step > 0; }, 10.0);
}

// Sets one limit through the node's reconfigure service, as `dynparam set` does; returns
// the value the node sends back as its configuration, and in `refused` the reason it gives.
double reconfigure(const std::string& name, double value, std::string* refused = nullptr) {
  dynamic_reconfigure::Reconfigure srv;
  dynamic_reconfigure::DoubleParameter d;
  d.name = name;
  d.value = value;
  srv.request.config.doubles.push_back(d);
  if (!ros::service::call("needle_sim/set_parameters", srv)) {
    ADD_FAILURE() << "set_parameters call failed";
    return std::nan("");
  }
  if (refused) {
    *refused = "(none returned)";
    for (const auto& s : srv.response.config.strs)
      if (s.name == "refused") *refused = s.value;
  }
  for (const auto& x : srv.response.config.doubles)
    if (x.name == name) return x.value;
  ADD_FAILURE() << "no " << name << " in the returned configuration";
  return std::nan("");
}

}  // namespace

class GuardSafety : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    nh_ = new ros::NodeHandle("needle_sim");
    clock_ = new needle_sim_test::SimClock(*nh_);
    node_ = new Node;
    Node* n = node_;
    subs_.push_back(nh_->subscribe<needle_sim::SimStatus>(
        "status", 5000, [n](const needle_sim::SimStatus::ConstPtr& s) { n->onStatus(s); }));
    subs_.push_back(nh_->subscribe<diagnostic_msgs::DiagnosticArray>(
        "/diagnostics", 100, [n](const diagnostic_msgs::DiagnosticArray::ConstPtr& a) { n->onDiag(a); }));
    subs_.push_back(
        nh_->subscribe<rosgraph_msgs::Log>("/rosout", 1000, [n](const rosgraph_msgs::Log::ConstPtr& l) { n->onLog(l); }));
    cmd_ = new ros::Publisher(nh_->advertise<geometry_msgs::PoseStamped>("needle/command_pose", 1000));
    other_ = new ros::Publisher(nh_->advertise<std_msgs::Bool>("/second_commander/enable", 10, true));
    spinner_ = new ros::AsyncSpinner(3);
    spinner_->start();
    ASSERT_TRUE(waitFor([] { return node_->size() > 20; }, 60.0));
    ASSERT_TRUE(waitFor([] { return cmd_->getNumSubscribers() > 0 && other_->getNumSubscribers() > 0; }, 20.0));
    ASSERT_TRUE(ros::service::waitForService("needle_sim/set_parameters", 10000));
  }
  static ros::NodeHandle* nh_;
  static needle_sim_test::SimClock* clock_;
  static Node* node_;
  static std::vector<ros::Subscriber> subs_;
  static ros::Publisher *cmd_, *other_;
  static ros::AsyncSpinner* spinner_;
};
ros::NodeHandle* GuardSafety::nh_;
needle_sim_test::SimClock* GuardSafety::clock_;
Node* GuardSafety::node_;
std::vector<ros::Subscriber> GuardSafety::subs_;
ros::Publisher *GuardSafety::cmd_, *GuardSafety::other_;
ros::AsyncSpinner* GuardSafety::spinner_;

// 1. Reconfigure that refuses: the node sees what was asked (no .cfg range clamps it) and
//    refuses a bad set whole; the caller gets the old value back.
TEST_F(GuardSafety, ReconfigureRefusesBadLimitsWholeAndKeepsTheOldOnes) {
  Node& n = *node_;
  const size_t log0 = n.logSize();
  const double inf = std::numeric_limits<double>::infinity();
  int refused = 0;
  for (double v : {1e9, inf, std::nan(""), -1.0, 0.0, 0.095}) {
    EXPECT_EQ(reconfigure("max_speed", v), 0.05) << "max_speed " << v << ": the old limit comes back";
    ++refused;
  }
  // The ERRORs name the rule or the ceiling.
  ASSERT_TRUE(waitFor([&] { return n.logged(log0, rosgraph_msgs::Log::ERROR, {"reconfigure refused"}) >= refused; }, 5.0));
  EXPECT_EQ(n.logged(log0, rosgraph_msgs::Log::ERROR, {"1e+09 m/s is above its ceiling ~max_speed_ceiling = 0.09 m/s"}), 1);
  EXPECT_EQ(n.logged(log0, rosgraph_msgs::Log::ERROR, {"0.095 m/s is above its ceiling ~max_speed_ceiling = 0.09"}), 1);
  EXPECT_EQ(n.logged(log0, rosgraph_msgs::Log::ERROR, {"'~max_speed': must be positive and finite"}), 4);  // inf, NaN, -1, 0
  // The caller's answer says why (#42: `dynparam set` prints nothing), and is cleared by a set
  // that is taken.
  std::string why;
  EXPECT_EQ(reconfigure("max_speed", 1e9, &why), 0.05);
  EXPECT_NE(why.find("1e+09 m/s is above its ceiling ~max_speed_ceiling = 0.09 m/s"), std::string::npos) << why;
  ++refused;
  // A valid set is taken (at the ceiling), and so is the way back.
  EXPECT_EQ(reconfigure("max_speed", 0.09, &why), 0.09);
  EXPECT_EQ(why, "");
  EXPECT_EQ(reconfigure("max_speed", 0.05), 0.05);
  // A set that fails in one value keeps the others too (the in-tissue turn limit above its
  // own ceiling of 0.5 rad/s, with a valid max_speed beside it).
  dynamic_reconfigure::Reconfigure srv;
  dynamic_reconfigure::DoubleParameter a, b;
  a.name = "max_speed", a.value = 0.02;
  b.name = "max_angular_speed_inserted", b.value = 0.8;
  srv.request.config.doubles = {a, b};
  ASSERT_TRUE(ros::service::call("needle_sim/set_parameters", srv));
  for (const auto& x : srv.response.config.doubles) {
    if (x.name == "max_speed") {
      EXPECT_EQ(x.value, 0.05);
    }
    if (x.name == "max_angular_speed_inserted") {
      EXPECT_EQ(x.value, 0.1);
    }
  }
  // Diagnostics count the refusals (1 Hz of simulated time).
  EXPECT_TRUE(waitFor([&] { return n.diagValue("simulation", "reconfigure_refused") == "8"; }, 10.0))
      << n.diagValue("simulation", "reconfigure_refused");
}

// 2. One source per needle: this process (rostest names it /guard_safety) and /second_commander.
TEST_F(GuardSafety, OneSourceCommandsTheNeedleTheOtherIsRejectedAndNamed) {
  Node& n = *node_;
  ASSERT_TRUE(resetAndWait(n));
  const uint64_t owner0 = n.count("owner");
  const size_t log0 = n.logSize();
  // This process commands first (the base where it is), then keeps streaming while the
  // second process streams 3 mm further back.
  cmd_->publish(pose(kBaseX));
  ASSERT_TRUE(waitFor([&] { return n.status().state == "running"; }, 5.0));
  std_msgs::Bool on;
  on.data = true;
  other_->publish(on);
  const ros::Time s0 = ros::Time::now();
  while ((ros::Time::now() - s0).toSec() < 1.0) {
    cmd_->publish(pose(kBaseX));
    ros::WallDuration(0.004).sleep();
  }
  // About 100 rejections (100 Hz for 1 s), and the needle never left this process's pose.
  std::cout << "owner rejections of the second process in 1 s: " << n.count("owner") - owner0 << " (more than 50)\n";
  EXPECT_GT(n.count("owner") - owner0, 50u);
  EXPECT_NEAR(n.lastSample().base.x(), kBaseX, 1e-12) << "the second source moved the needle";
  ASSERT_TRUE(waitFor([&] {
    return n.logged(log0, rosgraph_msgs::Log::WARN, {"rule 'owner'", "/second_commander", ros::this_node::getName()}) > 0;
  }, 5.0)) << "no warning naming both sources";
  // Silent for more than ~owner_timeout (0.5 s): the second process takes the needle and
  // moves it (3 mm at the speed limit); this process is now the one rejected.
  ASSERT_TRUE(simWait(n, 0.7));
  ASSERT_TRUE(waitFor([&] { return std::abs(n.lastSample().base.x() - (-0.038)) < 1e-9; }, 10.0));
  const uint64_t owner1 = n.count("owner");
  cmd_->publish(pose(kBaseX));
  ASSERT_TRUE(waitFor([&] { return n.count("owner") == owner1 + 1; }, 5.0));
  ASSERT_TRUE(simWait(n, 0.1));
  EXPECT_NEAR(n.lastSample().base.x(), -0.038, 1e-12);
  // An ~insert goal is refused while the second process streams, and holds the needle
  // against it once it is silent.
  actionlib::SimpleActionClient<needle_sim::InsertNeedleAction> ac(*nh_, "insert", false);
  ASSERT_TRUE(ac.waitForServer(ros::Duration(5.0)));
  needle_sim::InsertNeedleGoal goal;
  goal.point.x = 0.02, goal.point.y = kY, goal.point.z = kZ;
  goal.depth = 0.004;
  goal.speed = 0.01;
  ac.sendGoal(goal);
  ASSERT_TRUE(ac.waitForResult(ros::Duration(10.0)));
  EXPECT_EQ(ac.getState(), actionlib::SimpleClientGoalState::REJECTED);
  EXPECT_NE(ac.getState().getText().find("/second_commander"), std::string::npos) << ac.getState().getText();
  std_msgs::Bool off;
  off.data = false;
  other_->publish(off);
  ASSERT_TRUE(simWait(n, 0.6));
  ac.sendGoal(goal);
  ASSERT_TRUE(waitFor([&] { return ac.getState() == actionlib::SimpleClientGoalState::ACTIVE; }, 5.0));
  const uint64_t owner2 = n.count("owner");
  cmd_->publish(pose(-0.038));  // this process: rejected while the goal runs
  ASSERT_TRUE(waitFor([&] { return n.count("owner") == owner2 + 1; }, 5.0));
  ASSERT_TRUE(ac.waitForResult(ros::Duration(20.0)));
  EXPECT_EQ(ac.getState(), actionlib::SimpleClientGoalState::SUCCEEDED) << ac.getState().getText();
  EXPECT_NEAR(ac.getResult()->inserted, 0.004, 1e-6);
  // Done: the goal gave the needle back; this process commands it again.
  const double x = n.lastSample().base.x();
  cmd_->publish(pose(x - 0.001));
  ASSERT_TRUE(simWait(n, 0.2));
  EXPECT_NEAR(n.lastSample().base.x(), x - 0.001, 1e-9);
  EXPECT_EQ(n.count("owner"), owner2 + 1);
}

// 3. The tip watched. Insert 13 mm (tip 10 mm in), turn the axis 0.2 rad (at the in-tissue
//    limit), withdraw at the linear limit: the bent needle snaps back as it leaves.
TEST_F(GuardSafety, TheTipsSnapBackIsPredictedWarnedAndInDiagnostics) {
  Node& n = *node_;
  std_msgs::Bool off;
  off.data = false;
  other_->publish(off);
  ASSERT_TRUE(resetAndWait(n));
  ASSERT_TRUE(simWait(n, 0.6));  // any earlier owner silent
  const double peak0 = 0;
  // Straight in at 10 mm/s: the tip follows at about that speed, nothing warned.
  const ros::Time i0 = ros::Time::now();
  double x = kBaseX;
  while (x < kBaseX + 0.013) {
    x = std::min(kBaseX + 0.013, kBaseX + 0.01 * (ros::Time::now() - i0).toSec());
    cmd_->publish(pose(x));
    ros::WallDuration(0.004).sleep();
  }
  ASSERT_TRUE(simWait(n, 0.2));
  ASSERT_EQ(n.status().insertion_states[0], "inserted");
  const Eigen::Quaterniond yaw(Eigen::AngleAxisd(0.2, Eigen::Vector3d::UnitZ()));
  cmd_->publish(pose(x, yaw));
  ASSERT_TRUE(simWait(n, 2.3));  // 0.2 rad at ~max_angular_speed_inserted = 0.1 rad/s
  // Diagnostics report the straight insertion and the turn: within ~max_tip_speed (4 x 0.05).
  ASSERT_TRUE(simWait(n, 1.1));
  EXPECT_EQ(n.diagValue("tip_speed", "max_tip_speed"), "0.2");
  EXPECT_EQ(n.diagValue("tip_speed", "needle/tip_speed_over_limit_steps"), "0");
  // ~predict: the withdrawal, 20 mm back at 0.05 m/s (the linear limit), keeping the axis.
  needle_sim::PredictInsertion p;
  p.request.trajectory.header.frame_id = "tissue";
  needle_sim::NeedleWaypoint w;
  w.time_from_start = ros::Duration(0.4);
  w.pose = pose(x - 0.02, yaw).pose;
  p.request.trajectory.waypoints.push_back(w);
  p.request.duration = 0.6;
  ASSERT_TRUE(ros::service::call("needle_sim/predict", p));
  ASSERT_TRUE(p.response.success) << p.response.message;
  EXPECT_GT(p.response.max_tip_speed, 0.3) << "the snap-back, predicted at 10 ms steps";
  std::printf("predicted: largest tip speed %.4g m/s at %.3g s\n", p.response.max_tip_speed,
              p.response.max_tip_speed_time);
  EXPECT_GT(p.response.max_tip_speed_time, 0.0);
  EXPECT_LT(p.response.max_tip_speed_time, 0.6);
  // The same withdrawal, live.
  const size_t mark = n.size(), log0 = n.logSize();
  cmd_->publish(pose(x - 0.02, yaw));
  ASSERT_TRUE(simWait(n, 0.6));
  // The tip's speed, step to step, from ~status.
  double fastest = 0;
  {
    std::lock_guard<std::mutex> lk(n.m);
    for (size_t i = mark + 1; i < n.samples.size(); ++i) {
      const Sample &a = n.samples[i - 1], &b = n.samples[i];
      if (b.step != a.step + 1) continue;
      fastest = std::max(fastest, (b.tip - a.tip).norm() / (b.t - a.t));
    }
  }
  EXPECT_GT(fastest, 0.3) << "no snap-back to watch";
  std::printf("live: largest tip speed %.6g m/s over a step\n", fastest);
  ASSERT_TRUE(waitFor([&] {
    return n.logged(log0, rosgraph_msgs::Log::WARN, {"the tip moved at", "~max_tip_speed = 0.2 m/s"}) > 0;
  }, 5.0));
  // Diagnostics: tip_speed WARN, its peak the fastest step of ~status.
  ASSERT_TRUE(simWait(n, 1.1));
  double reported = peak0;
  bool warned = false;
  {
    std::lock_guard<std::mutex> lk(n.m);
    for (const auto& s : n.tip_reports) {
      warned = warned || s.level == diagnostic_msgs::DiagnosticStatus::WARN;
      for (const auto& kv : s.values)
        if (kv.key == "needle/tip_speed_peak") reported = std::max(reported, std::stod(kv.value));
    }
  }
  EXPECT_TRUE(warned);
  EXPECT_NEAR(reported, fastest, 1e-6 * fastest);
  EXPECT_GT(std::stoul(n.diagValue("tip_speed", "needle/tip_speed_over_limit_steps")), 0u);
}

// A ~predict request: the base 5 mm in from rest in `over` seconds, at time step dt.
needle_sim::PredictInsertion advanceBy5mm(double over, double dt) {
  needle_sim::PredictInsertion p;
  p.request.trajectory.header.frame_id = "tissue";
  needle_sim::NeedleWaypoint w;
  w.time_from_start = ros::Duration(over);
  w.pose = pose(kBaseX + 0.005).pose;
  p.request.trajectory.waypoints.push_back(w);
  p.request.dt = dt;
  return p;
}

// 4. ~predict's time step is bounded by ~predict_max_dt (10 x the scene's 1 ms).
TEST_F(GuardSafety, PredictRefusesATimeStepAboveTheMaximum) {
  Node& n = *node_;
  ASSERT_TRUE(resetAndWait(n));
  needle_sim::PredictInsertion p = advanceBy5mm(0.5, 1.0);
  ASSERT_TRUE(ros::service::call("needle_sim/predict", p));
  EXPECT_FALSE(p.response.success);
  EXPECT_NE(p.response.message.find("~predict_max_dt = 0.01"), std::string::npos) << p.response.message;
  EXPECT_TRUE(p.response.time.empty());
  p.request.dt = 0.01;  // at the bound: predicted, the tip at about the base's 10 mm/s
  ASSERT_TRUE(ros::service::call("needle_sim/predict", p));
  EXPECT_TRUE(p.response.success) << p.response.message;
  EXPECT_GT(p.response.max_tip_speed, 0.009);
  EXPECT_LT(p.response.max_tip_speed, 0.02);
}

// 5. (#40) A prediction longer than ~predict_max_wall (2 s here) is stopped and answered
//    unsuccessful, naming the parameter; it ran on a thread below every other of the node
//    (SCHED_IDLE); diagnostics count it.
namespace {
// Field `field` of /proc/PID/task/TID/stat (proc(5): 19 nice, 41 policy) of the thread named
// `name` in any process (-100: none).
int threadStat(const std::string& name, int field) {
  namespace fs = std::filesystem;
  for (const auto& proc : fs::directory_iterator("/proc")) {
    std::error_code ec;
    if (!fs::is_directory(proc.path() / "task", ec)) continue;
    for (const auto& task : fs::directory_iterator(proc.path() / "task", ec)) {
      std::ifstream comm(task.path() / "comm");
      std::string c;
      if (!std::getline(comm, c) || c != name) continue;
      std::ifstream statf(task.path() / "stat");
      std::string stat((std::istreambuf_iterator<char>(statf)), std::istreambuf_iterator<char>());
      std::istringstream rest(stat.substr(stat.rfind(')') + 2));  // fields from 3 (state) on
      std::string f;
      for (int i = 3; i <= field && rest >> f; ++i)
        if (i == field) return std::stoi(f);
    }
  }
  return -100;
}
}  // namespace

TEST_F(GuardSafety, APredictionStopsAtItsWallBudgetOnALowPriorityThread) {
  Node& n = *node_;
  ASSERT_TRUE(resetAndWait(n));
  needle_sim::PredictInsertion p = advanceBy5mm(99.0, 0.001);  // 99,000 steps: about 20 s of work
  const ros::WallTime t0 = ros::WallTime::now();
  ASSERT_TRUE(ros::service::call("needle_sim/predict", p));
  const double wall = (ros::WallTime::now() - t0).toSec();
  EXPECT_FALSE(p.response.success);
  EXPECT_NE(p.response.message.find("stopped by ~predict_max_wall = 2 s"), std::string::npos) << p.response.message;
  EXPECT_TRUE(p.response.time.empty());
  EXPECT_GE(p.response.compute_time, 2.0);
  EXPECT_LT(wall, 6.0) << "the budget did not stop it";
  std::printf("stopped: %s (%.2f s)\n", p.response.message.c_str(), wall);
  EXPECT_EQ(threadStat("ns_predict", 41), SCHED_IDLE) << "the predictions' thread's scheduling policy";
  EXPECT_TRUE(waitFor(
      [&] {
        const std::string v = n.diagValue("simulation", "predictions_stopped");
        return !v.empty() && std::stoul(v) >= 1;
      },
      10.0))
      << "diagnostics do not count the stopped prediction";
}

// 6. (#40) A newer request preempts the one under way (~predict_preempt, on by default): the
//    older is answered unsuccessful, "preempted", long before its budget; the newer is answered.
TEST_F(GuardSafety, ANewerPredictionPreemptsTheOneUnderWay) {
  Node& n = *node_;
  ASSERT_TRUE(resetAndWait(n));
  const std::string before = n.diagValue("simulation", "predictions_preempted");
  needle_sim::PredictInsertion old_request = advanceBy5mm(99.0, 0.001);  // 20 s of work, stopped at 2 s
  const ros::WallTime t0 = ros::WallTime::now();
  std::thread older([&] { EXPECT_TRUE(ros::service::call("needle_sim/predict", old_request)); });
  ros::WallDuration(0.5).sleep();  // the older one is under way
  needle_sim::PredictInsertion newer = advanceBy5mm(0.5, 0.01);
  ASSERT_TRUE(ros::service::call("needle_sim/predict", newer));
  older.join();
  const double wall = (ros::WallTime::now() - t0).toSec();
  EXPECT_TRUE(newer.response.success) << newer.response.message;
  EXPECT_FALSE(old_request.response.success);
  EXPECT_NE(old_request.response.message.find("preempted: a newer ~predict or ~steer request arrived"),
            std::string::npos)
      << old_request.response.message;
  EXPECT_LT(old_request.response.compute_time, 1.5) << "not preempted: it ran to its 2 s budget";
  EXPECT_LT(wall, 3.0);
  EXPECT_TRUE(waitFor(
      [&] {
        const std::string v = n.diagValue("simulation", "predictions_preempted");
        return !v.empty() && std::stoul(v) == (before.empty() ? 0 : std::stoul(before)) + 1;
      },
      10.0))
      << "diagnostics do not count the preempted prediction";
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "test_guard_safety");
  return RUN_ALL_TESTS();
}

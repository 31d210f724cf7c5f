// rostest of the numerical-failure path (failure.test, issue #39): the phantom unclamped
// under a strong gravity falls until the divergence check stops it (the core throws
// NumericalError at a step the test finds by running the same scene in its own process).
// The node then reports state `failed` with the core's message at that step, publishes
// nothing but its status, says ERROR in diagnostics, refuses ~predict; ~reset brings back
// the initial state, which runs (wrenches again, diagnostics no longer ERROR) and fails again
// at the same step. Simulated time owned by the test (sim_clock.hpp): nothing here is timed
// on the wall clock (waitFor's limits only end a test that hangs).
#include <gtest/gtest.h>
#include <diagnostic_msgs/DiagnosticArray.h>
#include <geometry_msgs/WrenchStamped.h>
#include <needle_sim/PredictInsertion.h>
#include <needle_sim/SimStatus.h>
#include <ros/ros.h>
#include <std_srvs/Trigger.h>

#include <mutex>
#include <string>
#include <vector>

#include "needle_sim/core/error.hpp"
#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/sim/simulation.hpp"
#include "sim_clock.hpp"
#include "wait_for.hpp"

namespace {

using needle_sim_test::waitFor;

struct Recorder {
  std::mutex m;
  needle_sim::SimStatus last;
  std::vector<std::pair<uint64_t, std::string>> steps;  // (step, state) of every status
  long wrenches = 0;
  std::vector<std::pair<int, std::string>> diags;  // the "simulation" status, in order
  needle_sim::SimStatus status() {
    std::lock_guard<std::mutex> lk(m);
    return last;
  }
  long wrenchCount() {
    std::lock_guard<std::mutex> lk(m);
    return wrenches;
  }
  size_t diagCount() {
    std::lock_guard<std::mutex> lk(m);
    return diags.size();
  }
  // The level and message of the first diagnostic after index `from` at `level` ("" if none).
  bool diagSince(size_t from, int level, std::string* msg = nullptr) {
    std::lock_guard<std::mutex> lk(m);
    for (size_t k = from; k < diags.size(); ++k)
      if (diags[k].first == level) {
        if (msg) *msg = diags[k].second;
        return true;
      }
    return false;
  }
};

}  // namespace

TEST(NeedleSimFailure, FailedStateErrorDiagnosticAndReset) {
  ros::NodeHandle nh("needle_sim");  // the node's private namespace
  // The failure the core itself gives for the node's scene and overrides.
  std::string scene_file;
  std::vector<std::string> overrides;
  ASSERT_TRUE(nh.getParam("scene", scene_file));
  ASSERT_TRUE(nh.getParam("set", overrides));
  long fail_step = -1;
  std::string fail_message;
  {
    needle_sim::Simulation sim(needle_sim::loadScene(scene_file, overrides));
    try {
      while (sim.stepIndex() < 10000) sim.step();
    } catch (const needle_sim::NumericalError& e) {
      fail_step = e.step();
      fail_message = e.what();
    }
  }
  // Long enough for a diagnostic report between a ~reset and the next failure: the node's
  // reports come every 1 or 2 s (its 1 s timer calls Updater::update(), which skips a call
  // that comes less than its period after the last report).
  ASSERT_GT(fail_step, 2500) << "the scene must run a while before it fails";
  ASSERT_LT(fail_step, 5000);
  std::cout << "the core fails at step " << fail_step << ": " << fail_message << "\n";

  Recorder R;
  auto s1 = nh.subscribe<needle_sim::SimStatus>("status", 5000, [&](const needle_sim::SimStatus::ConstPtr& s) {
    std::lock_guard<std::mutex> lk(R.m);
    R.last = *s;
    R.steps.emplace_back(s->step, s->state);
  });
  auto s2 = nh.subscribe<geometry_msgs::WrenchStamped>("needle/wrench", 5000, [&](const geometry_msgs::WrenchStamped::ConstPtr&) {
    std::lock_guard<std::mutex> lk(R.m);
    ++R.wrenches;
  });
  auto s3 = nh.subscribe<diagnostic_msgs::DiagnosticArray>("/diagnostics", 100, [&](const diagnostic_msgs::DiagnosticArray::ConstPtr& d) {
    std::lock_guard<std::mutex> lk(R.m);
    for (const auto& st : d->status)
      if (st.name.find("simulation") != std::string::npos) R.diags.emplace_back(st.level, st.message);
  });
  ros::AsyncSpinner spinner(2);
  spinner.start();
  // Every status from the first step on: connected before the clock starts.
  ASSERT_TRUE(waitFor([&] { return s1.getNumPublishers() > 0 && s2.getNumPublishers() > 0; }, 30.0));
  // The clock at the wall's pace (1 ms a tick): the 8x4x4 phantom steps in a fraction of that.
  needle_sim_test::SimClock clock(nh, 0.001);

  // 1. Running, then failed at the core's step with its message.
  ASSERT_TRUE(waitFor([&] { return R.status().state == "failed"; }, 60.0)) << "state " << R.status().state;
  const needle_sim::SimStatus failed = R.status();
  EXPECT_EQ(static_cast<long>(failed.step), fail_step);
  EXPECT_EQ(failed.message, fail_message);
  {
    std::lock_guard<std::mutex> lk(R.m);
    // Every step before it ran and was reported, in order: 1, 2, ..., fail_step - 1 running.
    long expect = 1;
    for (const auto& [step, state] : R.steps) {
      if (state == "failed") break;
      EXPECT_EQ(state, "running");
      ASSERT_EQ(static_cast<long>(step), expect) << "a status missing or out of order";
      ++expect;
    }
    EXPECT_EQ(expect, fail_step);
  }

  // 2. Failed, it publishes its status only (no wrench), stays at that step, and the
  //    diagnostics say ERROR with the failure; ~predict is refused naming ~reset.
  clock.sleep(0.1);  // (a wrench of the last good step may still be on its way)
  const long wrenches_failed = R.wrenchCount();
  EXPECT_EQ(wrenches_failed, fail_step - 1);
  const size_t diag_mark = R.diagCount();
  std::string error;
  ASSERT_TRUE(waitFor([&] { return R.diagSince(diag_mark, diagnostic_msgs::DiagnosticStatus::ERROR, &error); }, 20.0))
      << "no ERROR diagnostic after the failure";
  EXPECT_NE(error.find("numerical failure"), std::string::npos) << error;
  EXPECT_NE(error.find(fail_message), std::string::npos) << error;
  EXPECT_EQ(R.wrenchCount(), wrenches_failed) << "a wrench was published after the failure";
  EXPECT_EQ(R.status().state, "failed");
  EXPECT_EQ(static_cast<long>(R.status().step), fail_step);
  ASSERT_TRUE(ros::service::waitForService("needle_sim/predict", 5000));
  needle_sim::PredictInsertion pr;
  pr.request.trajectory.header.frame_id = "tissue";
  pr.request.duration = 0.1;
  ASSERT_TRUE(ros::service::call("needle_sim/predict", pr));
  EXPECT_FALSE(pr.response.success);
  EXPECT_NE(pr.response.message.find("failed"), std::string::npos) << pr.response.message;
  EXPECT_NE(pr.response.message.find("~reset"), std::string::npos) << pr.response.message;

  // 3. ~reset: the initial state, running again: steps from 1, wrenches again, diagnostics
  //    no longer ERROR.
  std_srvs::Trigger reset;
  ASSERT_TRUE(ros::service::call("needle_sim/reset", reset));
  EXPECT_TRUE(reset.response.success) << reset.response.message;
  ASSERT_TRUE(waitFor([&] { return R.status().state == "running"; }, 20.0)) << R.status().state;
  EXPECT_LT(static_cast<long>(R.status().step), fail_step / 2);
  ASSERT_TRUE(waitFor([&] { return R.wrenchCount() > wrenches_failed + 10; }, 20.0)) << "no wrench after ~reset";
  // A diagnostic computed after the reset (the first one after it may have been computed
  // before) that is not ERROR, before the run fails again.
  const size_t diag_reset = R.diagCount();
  ASSERT_TRUE(waitFor([&] {
    return R.diagSince(diag_reset, diagnostic_msgs::DiagnosticStatus::OK) ||
           R.diagSince(diag_reset, diagnostic_msgs::DiagnosticStatus::WARN) || R.status().state == "failed";
  }, 30.0));
  EXPECT_EQ(R.status().state, "running") << "no diagnostic other than ERROR between ~reset and the next failure";

  // 4. The same run again: it fails at the same step with the same message.
  ASSERT_TRUE(waitFor([&] { return R.status().state == "failed"; }, 60.0));
  EXPECT_EQ(static_cast<long>(R.status().step), fail_step);
  EXPECT_EQ(R.status().message, fail_message);
  clock.sleep(0.1);
  EXPECT_EQ(R.wrenchCount(), wrenches_failed + fail_step - 1);
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "test_failure");
  return RUN_ALL_TESTS();
}

// rostest of the node on the scenes the phantom tests do not reach (scenes.test, issue #39):
// an adaptive scene (phantom_insertion_adaptive: mesh changes built in the background), an
// immersed one (dbs_coarse: the brain surface, the brain shift at load, the STN's error bound
// off the stepping thread) and a multi-needle one (phantom_cannula_electrode: the cannula
// withdrawn, the electrode left), three nodes on one simulated clock owned by the test, each
// following its scene's own motion with ~deterministic_factor. What each node published,
// step by step, is checked against the core library running the same scene in this process:
// every step reported once and in order, the tips, DOFs and insertion states, every needle's
// wrench (the holder force, observables.hpp), the STN's error bound at the steps the node
// estimated it; and the facts of each scene (a mesh change, the shift's length, the cannula
// out and the electrode in).
#include <gtest/gtest.h>
#include <geometry_msgs/WrenchStamped.h>
#include <needle_sim/SimStatus.h>
#include <needle_sim/TargetState.h>
#include <ros/ros.h>

#include <cmath>
#include <map>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <vector>

#include "needle_sim/core/blas_threads.hpp"
#include "needle_sim/core/denormals.hpp"
#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/sim/live_loop.hpp"
#include "needle_sim/sim/observables.hpp"
#include "needle_sim/sim/simulation.hpp"
#include "sim_clock.hpp"
#include "wait_for.hpp"

namespace {

using needle_sim_test::waitFor;
using needle_sim::Vec3;

// The simulated time every node runs: the multi-needle scene's cannula is out by 2.4 s.
constexpr double kRunSeconds = 2.5;

struct NodeRun {
  std::string ns;
  std::string scene_file;
  std::vector<std::string> overrides;
  double rotation_drift = -1;  // the node's ~rotation_drift
  std::mutex m;
  std::vector<needle_sim::SimStatus> statuses;
  std::vector<std::vector<Vec3>> wrenches;  // per needle, in order
  std::vector<needle_sim::TargetState> targets;
  std::vector<ros::Subscriber> subs;

  explicit NodeRun(const std::string& name) : ns(name) {}
  size_t count() {
    std::lock_guard<std::mutex> lk(m);
    return statuses.size();
  }
  double simTime() {
    std::lock_guard<std::mutex> lk(m);
    return statuses.empty() ? 0.0 : statuses.back().sim_time;
  }
};

void subscribe(ros::NodeHandle& nh, NodeRun& run, const std::vector<std::string>& needles, bool targets) {
  ros::NodeHandle p(nh, run.ns);
  ASSERT_TRUE(p.getParam("scene", run.scene_file)) << run.ns;
  p.getParam("set", run.overrides);
  p.getParam("rotation_drift", run.rotation_drift);
  run.subs.push_back(p.subscribe<needle_sim::SimStatus>("status", 10000, [&run](const needle_sim::SimStatus::ConstPtr& s) {
    std::lock_guard<std::mutex> lk(run.m);
    run.statuses.push_back(*s);
  }));
  run.wrenches.resize(needles.size());
  for (size_t i = 0; i < needles.size(); ++i)
    run.subs.push_back(p.subscribe<geometry_msgs::WrenchStamped>(
        needles[i] + "/wrench", 10000, [&run, i](const geometry_msgs::WrenchStamped::ConstPtr& w) {
          std::lock_guard<std::mutex> lk(run.m);
          run.wrenches[i].emplace_back(w->wrench.force.x, w->wrench.force.y, w->wrench.force.z);
        }));
  if (targets)
    run.subs.push_back(p.subscribe<needle_sim::TargetState>("target/state", 10000, [&run](const needle_sim::TargetState::ConstPtr& t) {
      std::lock_guard<std::mutex> lk(run.m);
      if (t->name == "STN_L") run.targets.push_back(*t);
    }));
}

bool connected(NodeRun& run) {
  for (auto& s : run.subs)
    if (s.getNumPublishers() == 0) return false;
  return true;
}

Vec3 vec(const geometry_msgs::Point& p) { return Vec3(p.x, p.y, p.z); }

// The core library on the node's scene, stepped to every step the node reported: the node
// published each step once, in order, with the core's tips, DOFs, insertion states and holder
// forces. `each` is called with the core's simulation at the start (status nullptr) and after
// every step (the node's status of that step).
template <class Each>
void compareWithCore(NodeRun& run, Each each) {
  std::lock_guard<std::mutex> lk(run.m);
  needle_sim::flushDenormalsToZero();  // as the node's stepping thread
  needle_sim::setBlasThreads(1);        // as the node (~blas_threads)
  needle_sim::Scene scene = needle_sim::loadScene(run.scene_file, run.overrides);
  // As the node runs it (~deterministic_factor true): dbs_coarse with lagged rotations.
  needle_sim::applyLiveLoop(scene, {true, run.rotation_drift});
  needle_sim::Simulation::Options o;
  o.target_errors = !scene.targets.empty();
  needle_sim::Simulation sim(scene, o);
  ASSERT_GE(run.statuses.size(), static_cast<size_t>(kRunSeconds / scene.dt) - 2) << run.ns;
  needle_sim::Observables obs;
  double worst_tip = 0, worst_force = 0;
  each(sim, nullptr);
  for (size_t k = 0; k < run.statuses.size(); ++k) {
    const needle_sim::SimStatus& s = run.statuses[k];
    ASSERT_EQ(s.step, k + 1) << run.ns << ": a status missing or out of order";
    ASSERT_EQ(s.state, "running") << run.ns;
    sim.step();
    needle_sim::observe(sim, obs);
    ASSERT_EQ(s.dofs, static_cast<uint32_t>(obs.dofs)) << run.ns << " step " << s.step;
    ASSERT_EQ(s.tips.size(), obs.needles.size());
    for (size_t i = 0; i < obs.needles.size(); ++i) {
      worst_tip = std::max(worst_tip, (vec(s.tips[i]) - obs.needles[i].tip).norm());
      ASSERT_EQ(s.insertion_states[i], needle_sim::toString(obs.needles[i].state)) << run.ns << " step " << s.step;
      if (k < run.wrenches[i].size()) {
        const double d = (run.wrenches[i][k] - obs.needles[i].holder_force_base).norm();
        worst_force = std::max(worst_force, d);
      }
    }
    each(sim, &s);
  }
  for (const auto& w : run.wrenches) EXPECT_GE(w.size(), run.statuses.size()) << run.ns << ": a wrench per step";
  // The node steps the core as this process does (~deterministic_factor: the same factor
  // refreshes; one BLAS thread and subnormals flushed in both): the same numbers, bit for bit.
  EXPECT_EQ(worst_tip, 0.0) << run.ns;
  EXPECT_EQ(worst_force, 0.0) << run.ns;
  std::cout << run.ns << ": " << run.statuses.size() << " steps, largest tip difference " << worst_tip
            << " m, largest holder force difference " << worst_force << " N\n";
}

}  // namespace

TEST(NeedleSimScenes, AdaptiveImmersedAndMultiNeedleScenesStepAsTheCore) {
  ros::NodeHandle nh;
  NodeRun adaptive("adaptive"), immersed("immersed"), multi("multi");
  subscribe(nh, adaptive, {"needle"}, false);
  subscribe(nh, immersed, {"cannula", "electrode"}, true);
  subscribe(nh, multi, {"cannula", "electrode"}, false);
  ros::AsyncSpinner spinner(3);
  spinner.start();
  // Every message from the first step on: all connected (the nodes loaded) before the clock
  // starts; they do not step before it.
  ASSERT_TRUE(waitFor([&] { return connected(adaptive) && connected(immersed) && connected(multi); }, 60.0));
  {
    // Until every node has stepped kRunSeconds (each started its scene at the first /clock
    // it received), then the clock holds.
    needle_sim_test::SimClock clock(nh);
    for (NodeRun* r : {&adaptive, &immersed, &multi})
      EXPECT_TRUE(waitFor([&] { return r->simTime() >= kRunSeconds - 1e-9; }, 40 * kRunSeconds))
          << r->ns << " at " << r->simTime();
    clock.paused = true;
    ros::WallDuration(0.3).sleep();  // the last wrenches and target states on their way
  }
  spinner.stop();

  // Adaptive: the node's mesh changed (DOFs grew after the puncture), and every step is the
  // core's, mesh changes included.
  {
    const uint32_t start_dofs = adaptive.statuses.front().dofs;
    uint32_t most = start_dofs;
    bool estimated = false, inserted = false;
    compareWithCore(adaptive, [&](const needle_sim::Simulation&, const needle_sim::SimStatus* s) {
      if (!s) return;
      most = std::max(most, s->dofs);
      estimated = estimated || s->eta_relative > 0;
      inserted = inserted || s->insertion_states[0] == "inserted";
    });
    EXPECT_GT(most, start_dofs) << "no mesh change in the adaptive scene";
    EXPECT_TRUE(estimated);
    EXPECT_TRUE(inserted);
  }

  // Immersed: the brain shift at load (the left STN 6.5 mm from its planning position before
  // the cannula touches it), the cannula in the brain, and the STN's error bound the node
  // estimated off the stepping thread equal to the core's at the same step.
  {
    std::map<long, double> bounds;  // error_step -> bound the node published
    double first_shift = 0;
    {
      std::lock_guard<std::mutex> lk(immersed.m);
      ASSERT_FALSE(immersed.targets.empty()) << "no target/state";
      const auto& sh = immersed.targets.front().shift;
      first_shift = std::sqrt(sh.x * sh.x + sh.y * sh.y + sh.z * sh.z);
      const long last_step = static_cast<long>(immersed.statuses.back().step);
      for (const auto& t : immersed.targets)
        if (t.error_step >= 0 && t.error_step <= last_step) {
          EXPECT_TRUE(std::isfinite(t.displacement_error_bound) && t.displacement_error_bound > 0);
          bounds[t.error_step] = t.displacement_error_bound;
        }
    }
    EXPECT_NEAR(first_shift, 0.0065, 0.0065e-3);
    ASSERT_GE(bounds.size(), 5u) << "the node estimated the bound every ~target_error_period (0.2 s)";
    int compared = 0;
    bool inserted = false;
    // (error_step 0: the brain shift's own estimate, made at load, until the first one of the
    // error thread)
    compareWithCore(immersed, [&](const needle_sim::Simulation& sim, const needle_sim::SimStatus* s) {
      inserted = inserted || (s && s->insertion_states[0] == "inserted");
      auto it = bounds.find(sim.stepIndex());
      if (it == bounds.end()) return;
      needle_sim::Simulation copy(sim);  // as the node estimates: on a copy
      const double core = copy.targetError(copy.findTarget("STN_L")).bound;
      EXPECT_EQ(it->second, core) << "step " << it->first;
      ++compared;
    });
    EXPECT_EQ(compared, static_cast<int>(bounds.size())) << [&] {
      std::string k;
      for (const auto& [step, b] : bounds) k += std::to_string(step) + " ";
      return k;
    }();
    EXPECT_TRUE(inserted) << "the cannula never went into the brain";
  }

  // Multi-needle: both needles reported; at the end the cannula is out and the electrode in,
  // holding on its own (its wrench no longer the sheath's).
  {
    compareWithCore(multi, [](const needle_sim::Simulation&, const needle_sim::SimStatus*) {});
    std::lock_guard<std::mutex> lk(multi.m);
    const needle_sim::SimStatus& last = multi.statuses.back();
    ASSERT_EQ(last.needles.size(), 2u);
    EXPECT_EQ(last.needles[0], "cannula");
    EXPECT_EQ(last.insertion_states[0], "out");
    EXPECT_EQ(last.insertion_states[1], "inserted");
    EXPECT_NEAR(last.tips[1].x, 0.008, 1e-4);  // the electrode's tip 8 mm in
  }
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "test_scenes");
  return RUN_ALL_TESTS();
}

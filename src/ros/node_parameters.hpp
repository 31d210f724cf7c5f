#pragma once
// The node's private parameters, read once at start-up into one struct; every default and
// range is listed in doc/ros_api.md (the single source of them). Throws InputError naming
// the parameter ("~name") for a value out of range.
#include <ros/ros.h>

#include <array>
#include <string>
#include <vector>

#include "needle_sim/command/command_guard.hpp"
#include "node_assimilation.hpp"

namespace needle_sim {

struct NodeParameters {
  std::string scene_file;
  std::vector<std::string> overrides;  // ~set: key.path=value, as `needle_sim run --set`
  // ~deterministic_factor: false (default) swaps a background factor refresh in as soon as it
  // is ready (solver.linear.async_lag 0: no step waits for it); true keeps the scene's lag.
  bool deterministic_factor = false;
  // ~rotation_drift [rad]: the scene's solver.linear.rotation_drift in the node; < 0 (default):
  // the scene's if it sets one, else kLiveRotationDrift for nearly incompressible tissue
  // (sim/live_loop.hpp).
  double rotation_drift = -1;
  std::string tissue_frame = "tissue";
  std::string parent_frame;             // "": the tissue frame is a root of the tf tree
  std::array<double, 7> tissue_pose{{0, 0, 0, 0, 0, 0, 1}};  // parent -> tissue: x y z qx qy qz qw
  bool publish_tissue_transform = true;  // with a parent frame: broadcast it (static)
  std::string command_source = "topic";  // topic | scene | tf
  std::string needle_base_frame;         // tf commands, one needle: the base frame to follow
  bool allow_empty_frame = false;        // an empty frame_id means ~tissue_frame
  std::string wrench_frame = "base";     // base (<needle>_base) | tissue
  // ~<needle>/wrench between the steps of a scene slower than this [Hz] (the wall-clock pace
  // only; 0: once per step): extrapolated from the base's motion (needle/holder_wrench.hpp).
  double wrench_rate = 1000;
  CommandLimits limits;                  // workspace box filled from the scene
  // ~<limit>_ceiling: start-up only; no limit above them, at start-up or by reconfigure.
  LimitCeilings ceilings;
  // ~max_tip_speed [m/s]: a tip faster than this over a step is warned about (diagnostics
  // tip_speed); 0 (the default): 4 times the current ~max_speed, following reconfigure (a
  // puncture at the speed limit moved the tip at up to 2.8 times it; the snap of #39: 32 times).
  double max_tip_speed = 0;
  bool as_fast_as_possible = false;
  double display_rate = 30;
  // ~field_rate [Hz]: the tissue's fields (~tissue/surface, ~tissue/deformation,
  // ~tissue/error_markers) at most this often, within ~display_rate: the DBS brain's surface is
  // 57,000 triangles, 6.9 MB a message; at 30 Hz its building, sending and a subscriber's
  // reading took more than a core of the two (doc/benchmarks.md "Bounded step time").
  double field_rate = 5;
  double display_range = 0;   // [m] top of the colour scale; 0: adapts slowly to the motion
  double display_range_min = 1e-7;  // [m] the adaptive range never goes below this
  double output_period = 0.001;
  int blas_threads = 1;
  // ~setup_threads: BLAS threads while the scene loads (the brain-shift pre-step, before any
  // step; Simulation::setSetupThreads); 0: every core (at most 8). One by default: a robot's
  // machine is shared, and OpenBLAS's spinning threads made a busy machine's load 2-4x slower.
  int setup_threads = 1;
  // ~realtime_priority: SCHED_FIFO priority of the stepping thread (1-99; 0: the default
  // scheduler; -1, the default: kAutoRealtimePriority where the process may take it, else the
  // default scheduler). A control loop's simulator, like the loop itself, needs it to keep its
  // deadlines on a loaded machine: on the default scheduler the DBS scene's steps waited for
  // the clients' and the output's threads (doc/benchmarks.md "Bounded step time"). An explicit
  // priority the process may not take is warned about; the node runs on.
  int realtime_priority = -1;
  static constexpr int kAutoRealtimePriority = 10;
  double predict_dt = 0.01, predict_sample_period = 0.05;
  // ~predict_max_dt [s]: the coarsest time step a ~predict or ~steer request may ask for;
  // 0 (the default): 10 times the scene's dt (resolved once the scene is loaded).
  double predict_max_dt = 0;
  int predict_max_steps = 100000;
  // ~predict_max_wall [s]: the wall time one ~predict or ~steer request may take (0: no limit);
  // a request over it is stopped and answered unsuccessful.
  double predict_max_wall = 5.0;
  // ~predict_preempt: a ~predict or ~steer request under way is cancelled when a newer one
  // arrives (answered unsuccessful, "preempted"); false: requests are answered in turn.
  bool predict_preempt = true;
  // ~preflight_wall [s]: at start, this much wall time of the scene's own motion on a copy,
  // paced at dt, says whether the scene keeps real time here (0: no pre-flight).
  double preflight_wall = 2.0;
  double insert_speed = 0.005;          // [m/s] default speed of ~insert goals
  double target_error_period = 0.2;     // [s] goal-oriented error bound of the targets this often (0: off)
  double target_error_duty = 0.25;      // at most this share of the wall time spent estimating (1: back to back)
  double deadline_warn_fraction = 0.05;  // diagnostics WARN above this share of late steps / skipped ticks
  AssimilationParameters assimilation;   // ~assimilation/*: measurements in, online estimates out
};

NodeParameters readParameters(const ros::NodeHandle& pnh);

}  // namespace needle_sim

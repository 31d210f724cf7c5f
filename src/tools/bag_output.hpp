#pragma once
// A run's outputs written as a rosbag on the node's topic names (doc/cli.md, "run
// --out-bag"), so that a recorded session and the model can be compared offline with the
// usual ROS tools (rosbag info/play, rqt_plot, rviz): per step <ns>/status
// (needle_sim/SimStatus), <ns>/<needle>/wrench (geometry_msgs/WrenchStamped, in
// <needle>_base), and with targets <ns>/target/state (needle_sim/TargetState, one per
// target) and <ns>/target (the first target, geometry_msgs/PointStamped); <ns>/<needle>/path
// (nav_msgs/Path, the centre line in the pose convention) every `path_period` seconds of
// simulated time. The messages are built by the node's own conversions (src/ros), so the
// bag holds what the node would have published. Stamps: origin + simulated time (origin:
// the input bag's start when the run replays one, else 0).
#include <memory>
#include <string>

#include "needle_sim/core/error.hpp"
#include "needle_sim/sim/observables.hpp"
#include "needle_sim/sim/simulation.hpp"

#ifdef NEEDLE_SIM_WITH_ROS
#include <rosbag/bag.h>

namespace needle_sim {

class BagOutput {
 public:
  // Throws std::runtime_error when the bag cannot be written.
  BagOutput(const std::string& path, const std::string& ns, const Simulation& sim, double origin,
            double path_period = 1.0 / 30);
  ~BagOutput();
  // After each step.
  void record(const Simulation& sim, double step_ms);
  void close();
  long messages() const { return messages_; }

 private:
  rosbag::Bag bag_;
  std::string ns_;
  std::shared_ptr<const ObservableNames> names_;
  Observables obs_;
  double origin_, path_period_, next_path_ = 0, step_ms_max_ = 0;
  long messages_ = 0;
  uint64_t unconverged_ = 0;
  bool open_ = false;
};

}  // namespace needle_sim
#else
namespace needle_sim {

// Built without ROS (NEEDLE_SIM_ROS OFF): the node's messages do not exist, --out-bag is refused.
class BagOutput {
 public:
  BagOutput(const std::string&, const std::string&, const Simulation&, double, double = 0) {
    throw InputError("", "--out-bag", "this needle_sim was built without ROS (NEEDLE_SIM_ROS=OFF): it cannot write the node's messages");
  }
  void record(const Simulation&, double) {}
  void close() {}
  long messages() const { return 0; }
};

}  // namespace needle_sim
#endif

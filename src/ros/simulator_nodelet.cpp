// needle_sim/SimulatorNodelet: the same SimulatorRos inside a nodelet manager.
#include <nodelet/nodelet.h>
#include <pluginlib/class_list_macros.hpp>

#include <memory>

#include "needle_sim/core/error.hpp"
#include "needle_sim/ros/simulator_ros.hpp"

namespace needle_sim {

class SimulatorNodelet : public nodelet::Nodelet {
 private:
  void onInit() override {
    try {
      sim_ = std::make_unique<SimulatorRos>(getNodeHandle(), getPrivateNodeHandle());
    } catch (const InputError& e) {
      NODELET_FATAL("needle_sim: %s", e.what());
    }
  }
  std::unique_ptr<SimulatorRos> sim_;
};

}  // namespace needle_sim

PLUGINLIB_EXPORT_CLASS(needle_sim::SimulatorNodelet, nodelet::Nodelet)

#pragma once
// dynamic_reconfigure of the node's limits (cfg/Limits.cfg): max_speed, the angular limits,
// the stamp windows, the quaternion tolerance, the workspace margin, the display rate. A
// change is checked like the start-up parameters (CommandLimits::validate); a set that
// fails is refused whole: the previous values stay and are sent back to the client.
#include <dynamic_reconfigure/server.h>
#include <needle_sim/LimitsConfig.h>

#include <functional>

#include "needle_sim/command/command_guard.hpp"

namespace needle_sim {

class LimitsReconfigure {
 public:
  LimitsReconfigure(ros::NodeHandle& pnh, CommandGuard& guard, std::function<void(double)> set_display_rate);

 private:
  void onChange(needle_sim::LimitsConfig& c, uint32_t level);
  CommandGuard& guard_;
  std::function<void(double)> set_display_rate_;
  double display_rate_ = 30;
  boost::recursive_mutex mutex_;
  dynamic_reconfigure::Server<needle_sim::LimitsConfig> server_;
};

}  // namespace needle_sim

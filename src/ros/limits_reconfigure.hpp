#pragma once
// dynamic_reconfigure of the node's limits (cfg/Limits.cfg): max_speed, the angular limits,
// the stamp windows, the quaternion tolerance, the workspace margin, the display rate. A
// change is checked like the start-up parameters (CommandLimits::validate); a set that
// fails is refused whole: the previous values stay and are sent back to the client.
#include <dynamic_reconfigure/server.h>
#include <needle_sim/LimitsConfig.h>

#include <atomic>
#include <functional>
#include <mutex>
#include <string>

#include "needle_sim/command/command_guard.hpp"

namespace needle_sim {

class LimitsReconfigure {
 public:
  LimitsReconfigure(ros::NodeHandle& pnh, CommandGuard& guard, std::function<void(double)> set_display_rate);
  // Why the last change was refused ("" if it was taken), and how many were refused.
  std::string lastRefusal() const;
  unsigned long refusals() const { return refusals_; }

 private:
  void onChange(needle_sim::LimitsConfig& c, uint32_t level);
  CommandGuard& guard_;
  std::function<void(double)> set_display_rate_;
  double display_rate_ = 30;
  mutable std::mutex refusal_mutex_;
  std::string last_refusal_;
  std::atomic<unsigned long> refusals_{0};
  boost::recursive_mutex mutex_;
  dynamic_reconfigure::Server<needle_sim::LimitsConfig> server_;
};

}  // namespace needle_sim

#include "limits_reconfigure.hpp"

#include <cmath>

#include "needle_sim/core/error.hpp"

namespace needle_sim {

LimitsReconfigure::LimitsReconfigure(ros::NodeHandle& pnh, CommandGuard& guard, std::function<void(double)> set_rate)
    : guard_(guard), set_display_rate_(std::move(set_rate)), server_(mutex_, pnh) {
  pnh.param("display_rate", display_rate_, display_rate_);
  server_.setCallback([this](needle_sim::LimitsConfig& c, uint32_t level) { onChange(c, level); });
}

void LimitsReconfigure::onChange(needle_sim::LimitsConfig& c, uint32_t) {
  CommandLimits l = guard_.limits();
  const CommandLimits old = l;
  l.max_speed = c.max_speed;
  l.max_angular_speed = c.max_angular_speed;
  l.max_angular_speed_inserted = c.max_angular_speed_inserted;
  l.max_future = c.max_future;
  l.command_timeout = c.command_timeout;
  l.quaternion_tolerance = c.quaternion_tolerance;
  l.workspace_margin = c.workspace_margin;
  try {
    if (!(c.display_rate > 0) || !std::isfinite(c.display_rate))
      throw InputError("", "~display_rate", "must be > 0 and finite");
    guard_.setLimits(l);  // checked as at start-up and against the ceilings
  } catch (const InputError& e) {
    ROS_ERROR("needle_sim: reconfigure refused whole, the limits stay as they were and are sent back to the caller: %s",
              e.what());
    {
      std::lock_guard<std::mutex> lk(refusal_mutex_);
      last_refusal_ = e.what();
    }
    ++refusals_;
    c.max_speed = old.max_speed;
    c.max_angular_speed = old.max_angular_speed;
    c.max_angular_speed_inserted = old.max_angular_speed_inserted;
    c.max_future = old.max_future;
    c.command_timeout = old.command_timeout;
    c.quaternion_tolerance = old.quaternion_tolerance;
    c.workspace_margin = old.workspace_margin;
    c.display_rate = display_rate_;
    c.refused = e.what();  // the caller's answer says why (dynparam set prints nothing)
    return;
  }
  {
    std::lock_guard<std::mutex> lk(refusal_mutex_);
    last_refusal_.clear();
  }
  c.refused.clear();
  display_rate_ = c.display_rate;
  set_display_rate_(c.display_rate);
  ROS_INFO("needle_sim: limits now max_speed %g m/s, max_angular_speed %g rad/s (%g inserted), workspace_margin %g m",
           l.max_speed, l.max_angular_speed, l.max_angular_speed_inserted, l.workspace_margin);
}

std::string LimitsReconfigure::lastRefusal() const {
  std::lock_guard<std::mutex> lk(refusal_mutex_);
  return last_refusal_;
}

}  // namespace needle_sim

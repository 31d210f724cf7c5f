#pragma once
// Shared by the rostests that own the clock (/use_sim_time): a thread publishes /clock in
// 1 ms steps of simulated time, paced at half the wall rate so that the node keeps up on two
// cores (or every `wall_period` seconds of wall time); `paused` holds the clock where it is.
#include <ros/ros.h>
#include <rosgraph_msgs/Clock.h>

#include <atomic>
#include <cmath>
#include <thread>

namespace needle_sim_test {

struct SimClock {
  std::atomic<long> ms{1000};  // simulated time in ms, starting at 1 s
  std::atomic<bool> run{true}, paused{false};
  std::thread thread;
  explicit SimClock(ros::NodeHandle& nh, double wall_period = 0.002) {
    ros::Publisher pub = nh.advertise<rosgraph_msgs::Clock>("/clock", 10);
    thread = std::thread([this, pub, wall_period]() mutable {
      while (run) {
        rosgraph_msgs::Clock c;
        c.clock.fromNSec(static_cast<uint64_t>(paused ? ms.load() : ms.fetch_add(1)) * 1000000ULL);
        pub.publish(c);
        ros::WallDuration(wall_period).sleep();
      }
    });
  }
  // Waits (on the wall clock, at most a generous limit) until `seconds` of simulated time passed.
  bool sleep(double seconds) {
    const long until = ms + static_cast<long>(std::lround(seconds * 1000));
    const ros::WallTime limit = ros::WallTime::now() + ros::WallDuration(10 * seconds + 10);
    while (ms < until && ros::ok() && ros::WallTime::now() < limit) ros::WallDuration(0.001).sleep();
    return ms >= until;
  }
  ~SimClock() {
    run = false;
    thread.join();
  }
};

}  // namespace needle_sim_test

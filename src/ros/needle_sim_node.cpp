// needle_sim_node: the simulator as a ROS node (see simulator_ros.hpp for its interface).
//   rosrun needle_sim needle_sim_node _scene:=$(rospack find needle_sim)/config/scenes/phantom_insertion_8x4x4.yaml
#include <ros/ros.h>

#include "needle_sim/core/blas_threads.hpp"
#include "needle_sim/core/error.hpp"
#include "needle_sim/ros/simulator_ros.hpp"

int main(int argc, char** argv) {
  needle_sim::limitOpenMpThreads(argv);
  ros::init(argc, argv, "needle_sim");
  ros::NodeHandle nh, pnh("~");
  try {
    needle_sim::SimulatorRos sim(nh, pnh);
    // Two callback threads: a slow service call never delays the timer or the commands.
    ros::MultiThreadedSpinner spinner(2);
    spinner.spin();
  } catch (const needle_sim::InputError& e) {
    ROS_FATAL("needle_sim: %s", e.what());
    return 2;
  }
  return 0;
}

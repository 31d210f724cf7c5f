// needle_sim_node: the simulator as a ROS node (see simulator_ros.hpp for its interface).
//   rosrun needle_sim needle_sim_node _scene:=$(rospack find needle_sim)/config/scenes/phantom_insertion_8x4x4.yaml
#include <ros/ros.h>

#include <cstdio>
#include <string>

#include "needle_sim/core/blas_threads.hpp"
#include "needle_sim/core/denormals.hpp"
#include "needle_sim/core/heap_retention.hpp"
#include "needle_sim/core/error.hpp"
#include "needle_sim/ros/simulator_ros.hpp"

int main(int argc, char** argv) {
  for (int i = 1; i < argc; ++i)
    if (std::string(argv[i]) == "--help" || std::string(argv[i]) == "-h") {
      std::printf(
          "needle_sim_node: the needle insertion simulator as a ROS node.\n"
          "  rosrun needle_sim needle_sim_node _scene:=SCENE.yaml [_command_source:=topic|scene|tf] [_param:=value ...]\n"
          "  roslaunch needle_sim sim.launch [scene:=...] [rviz:=true]\n"
          "Topics, services, the ~insert action and every parameter with its default: doc/ros_api.md\n"
          "(installed: $(rospack find needle_sim)/doc/ros_api.md).\n");
      return 0;
    }
  needle_sim::limitOpenMpThreads(argv);
  // As the tool: threads made later inherit the flush-to-zero mode (the stepping thread also
  // sets it itself, for the nodelet).
  needle_sim::flushDenormalsToZero();
  needle_sim::retainFreedHeap();
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

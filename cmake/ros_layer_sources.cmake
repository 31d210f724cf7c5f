# The ROS layer's sources (library needle_sim_ros), relative to the package root: the package's
# CMakeLists.txt and test/tsan_ros/CMakeLists.txt (the same layer under ThreadSanitizer).
set(NEEDLE_SIM_ROS_LAYER_SOURCES
  src/ros/simulator_ros.cpp
  src/ros/step_outputs.cpp
  src/ros/command_input.cpp
  src/ros/services.cpp
  src/ros/steer_service.cpp
  src/ros/display_outputs.cpp
  src/ros/insert_action.cpp
  src/ros/limits_reconfigure.cpp
  src/ros/node_parameters.cpp
  src/ros/output_queue.cpp
  src/ros/conversions.cpp
  src/ros/node_assimilation.cpp)

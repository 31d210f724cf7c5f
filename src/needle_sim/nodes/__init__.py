"""ROS programs (rospy): the scripted insertion of sim.launch, the /use_sim_time clean-up of
replay.launch, and the node's benchmarks (doc/benchmarks.md); each module's main()."""

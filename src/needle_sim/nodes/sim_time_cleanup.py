"""Removes /use_sim_time from the parameter server when its launch ends (replay.launch):
roslaunch leaves the parameters it set on a running master, and a node started later with
/use_sim_time still true waits for a /clock that never comes."""
import rosgraph
import rospy


def main():
    rospy.init_node("sim_time_cleanup", anonymous=True)
    master = rosgraph.Master(rospy.get_name())

    def cleanup():
        try:
            if master.hasParam("/use_sim_time"):
                master.deleteParam("/use_sim_time")
        except Exception as e:  # the master went first: nothing is left behind then
            print("sim_time_cleanup: %s" % e)

    rospy.on_shutdown(cleanup)
    rospy.spin()


if __name__ == "__main__":
    main()

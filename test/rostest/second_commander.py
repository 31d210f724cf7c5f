#!/usr/bin/python3
"""A second process commanding the same needle (rostest guard_safety.test, issue #39): while
enabled (std_msgs/Bool on ~enable) it sends the base pose (~x, 0.01, 0.01), axis along x,
on /needle_sim/needle/command_pose at 100 Hz of ROS time, stamped now."""
import rospy
from geometry_msgs.msg import PoseStamped
from std_msgs.msg import Bool


def main():
    rospy.init_node("second_commander")
    x = rospy.get_param("~x", -0.038)
    pub = rospy.Publisher("/needle_sim/needle/command_pose", PoseStamped, queue_size=10)
    enabled = [False]
    rospy.Subscriber("~enable", Bool, lambda m: enabled.__setitem__(0, m.data))
    rate = rospy.Rate(100)
    while not rospy.is_shutdown():
        if enabled[0]:
            p = PoseStamped()
            p.header.stamp = rospy.Time.now()
            p.header.frame_id = "tissue"
            p.pose.position.x, p.pose.position.y, p.pose.position.z = x, 0.01, 0.01
            p.pose.orientation.w = 1.0
            pub.publish(p)
        try:
            rate.sleep()
        except (rospy.ROSTimeMovedBackwardsException, rospy.ROSInterruptException):
            pass


if __name__ == "__main__":
    main()

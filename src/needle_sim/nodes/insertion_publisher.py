"""Scripted needle insertion for needle_sim_node with ~command_source: topic, so that
`roslaunch needle_sim sim.launch scripted:=true` shows a full insertion without a robot.

Publishes geometry_msgs/PoseStamped on /<~node>/<needle>/command_pose at ~rate: the base advances along
~direction from ~base at ~speed by ~depth, holds ~hold seconds, and is withdrawn at the same
speed, then the script exits. The needle axis is the pose's x axis.

Parameters (private): ~node (needle_sim: the simulator's name), ~needle (needle), ~base ([-0.035, 0.01, 0.01]), ~direction ([1, 0, 0]),
~speed (0.01 m/s), ~depth (0.023 m), ~hold (0.2 s), ~rate (100 Hz), ~start_delay (1 s: after the node
has subscribed).
"""
import math

import rospy
from geometry_msgs.msg import PoseStamped


def quaternion_from_x_to(d):
    # Smallest rotation carrying (1, 0, 0) onto the unit vector d.
    x, y, z = d
    w = 1.0 + x
    if w < 1e-9:  # opposite: half turn about z
        return (0.0, 0.0, 1.0, 0.0)
    q = (w, 0.0, -z, y)
    n = math.sqrt(sum(c * c for c in q))
    return tuple(c / n for c in q)


def main():
    rospy.init_node("insertion_publisher")
    node = rospy.get_param("~node", "needle_sim")
    needle = rospy.get_param("~needle", "needle")
    base = rospy.get_param("~base", [-0.035, 0.01, 0.01])
    d = rospy.get_param("~direction", [1.0, 0.0, 0.0])
    speed = rospy.get_param("~speed", 0.01)
    depth = rospy.get_param("~depth", 0.023)
    hold = rospy.get_param("~hold", 0.2)
    rate_hz = rospy.get_param("~rate", 100.0)
    n = math.sqrt(sum(c * c for c in d))
    if len(base) != 3 or len(d) != 3 or n == 0 or speed <= 0 or depth < 0 or rate_hz <= 0:
        rospy.logfatal("insertion_publisher: invalid parameters (base, direction: 3 numbers; speed, rate > 0)")
        return 2
    d = [c / n for c in d]
    w, qx, qy, qz = quaternion_from_x_to(d)
    pub = rospy.Publisher("/%s/%s/command_pose" % (node, needle), PoseStamped, queue_size=10)
    # The node subscribes once it has loaded the scene and run its pre-flight (seconds): the
    # insertion starts from there, not from this script's own start.
    while pub.get_num_connections() == 0 and not rospy.is_shutdown():
        rospy.sleep(0.05)
    rospy.sleep(rospy.get_param("~start_delay", 1.0))
    t_in = depth / speed
    t0 = rospy.Time.now()
    rate = rospy.Rate(rate_hz)
    while not rospy.is_shutdown():
        t = (rospy.Time.now() - t0).to_sec()
        if t <= t_in:
            s = speed * t
        elif t <= t_in + hold:
            s = depth
        elif t <= 2 * t_in + hold:
            s = depth - speed * (t - t_in - hold)
        else:
            break
        msg = PoseStamped()
        msg.header.stamp = rospy.Time.now()
        msg.header.frame_id = "tissue"
        msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (b + s * c for b, c in zip(base, d))
        msg.pose.orientation.w, msg.pose.orientation.x, msg.pose.orientation.y, msg.pose.orientation.z = w, qx, qy, qz
        pub.publish(msg)
        rate.sleep()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The ROS node's overhead beyond the core step: subscribes to every output of a running
needle_sim node (so that the heavy ones are built) and reads, from `status`, the core step
time and the time the stepping thread spent on the outputs (publish_ms), over ~seconds; and,
from the diagnostics, the time the output thread (which builds and sends the messages, on
the other core) spent per step.

Sample run (the phantom insertion, scripted by the scene):

    source devel/setup.bash
    roslaunch needle_sim sim.launch &
    scripts/node_overhead.py --seconds 4
"""
import argparse
import statistics
import threading

import rospy
from geometry_msgs.msg import WrenchStamped
from nav_msgs.msg import Path
from diagnostic_msgs.msg import DiagnosticArray
from needle_sim.msg import SimStatus
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import Marker, MarkerArray


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--needle", default="needle")
    ap.add_argument("--node", default="needle_sim", help="the node's name: its topics are under it")
    args = ap.parse_args(rospy.myargv()[1:])
    rospy.init_node("node_overhead", anonymous=True)
    lock = threading.Lock()
    step, pub, counts = [], [], {}
    last_step = [None]
    out = []  # (step, output_thread_ms_total) at each diagnostics message

    def count(name):
        def cb(_):
            with lock:
                counts[name] = counts.get(name, 0) + 1
        return cb

    def on_status(m):
        with lock:
            last_step[0] = m.step
            if m.step_ms > 0:
                step.append(m.step_ms)
                pub.append(m.publish_ms)

    def on_diag(m):
        for st in m.status:
            for kv in st.values:
                if kv.key == "output_thread_ms_total":
                    with lock:
                        if last_step[0] is not None:
                            out.append((last_step[0], float(kv.value)))

    subs = [rospy.Subscriber(args.node + "/status", SimStatus, on_status),
            rospy.Subscriber("/diagnostics", DiagnosticArray, on_diag),
            rospy.Subscriber(args.node + "/" + args.needle + "/wrench", WrenchStamped, count("wrench")),
            rospy.Subscriber(args.node + "/" + args.needle + "/path", Path, count("path")),
            rospy.Subscriber(args.node + "/tissue/deformation", PointCloud2, count("deformation")),
            rospy.Subscriber(args.node + "/tissue/surface", Marker, count("surface")),
            rospy.Subscriber(args.node + "/tissue/error_markers", MarkerArray, count("error_markers"))]
    rospy.sleep(1.0)  # let the subscriptions settle
    with lock:
        step.clear()
        pub.clear()
        counts.clear()
        out.clear()
    rospy.sleep(args.seconds)
    with lock:
        if not step:
            raise SystemExit("node_overhead: no status received (is the node running?)")
        share = sum(pub) / sum(step)
        print(f"steps: {len(step)}, messages: {counts}")
        print(f"core step median {statistics.median(step):.3f} ms, publish median {statistics.median(pub):.3f} ms, "
              f"publish p95 {sorted(pub)[int(0.95 * (len(pub) - 1))]:.3f} ms, overhead (sum publish / sum step) "
              f"{100 * share:.1f} %")
        if len(out) >= 2 and out[-1][0] > out[0][0]:
            per_step = (out[-1][1] - out[0][1]) / (out[-1][0] - out[0][0])
            print(f"output thread {per_step:.3f} ms per step ({100 * per_step / statistics.mean(step):.1f} % of the mean "
                  f"step, on the other core; {out[-1][0] - out[0][0]} steps between diagnostics)")
    del subs


if __name__ == "__main__":
    main()

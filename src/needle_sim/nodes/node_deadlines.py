"""Does the ROS node keep its deadlines over a whole insertion with a client streaming poses?
(issue #18, doc/benchmarks.md "Bounded step time"). Acts as the robot: streams
geometry_msgs/PoseStamped base poses to a running needle_sim node (~command_source: topic) at
--rate Hz along a straight insertion (advance --depth at --speed, hold, withdraw), and reads
the node's ~status: steps done, late steps (finished more than a period after they were due)
and skipped ticks (a tick that found the previous step not started), counted over the
insertion (differences of the lifetime counters), with the machine's load average.

    source devel/setup.bash
    roslaunch needle_sim sim.launch scene:=$PWD/config/scenes/phantom_insertion_adaptive.yaml command_source:=topic &
    scripts/node_deadlines.py --rate 500

With --subscribe-all, every topic of the node, /tf and /diagnostics are subscribed to
(undecoded), as rviz and a monitor would: the node builds the heavy outputs only when they
are. For another scene give its needle's rest pose and depth, e.g. the gel demo:
--base -0.062 0.015 0.015 --depth 0.045.

With --scene NAME (a scene the node runs, by name or path), every needle of the scene is
streamed its own motion from the scene file (base, advance and roll keyframes, as
`needle_sim check NAME --json` reads them) at --rate Hz, over the scene's duration: the load
of the scene's insertion with the robot's stream in place of the scene's clock (the node
started with `command_source:=topic`); --base, --depth and the other motion options are then
not used.

With --predict-steps N, a ~predict request of N steps at --predict-dt is sent 0.2 s into the
insertion, from a thread of its own (as a planner beside the robot's loop would), and a second
line reports it: its wall time, whether the node stopped it (~predict_max_wall), and the late
steps and skipped ticks of the live loop while it ran.

With --echo-wrench NOISE, the client also acts as a force sensor: every --echo-every-th
~<needle>/wrench is sent back to ~<needle>/measured_wrench with Gaussian noise of NOISE [N]
(seed 1), stamped as it came; for a node with ~assimilation/keys (and wrench_noise), a further
line reports the last ~estimate: from its own force, the node must find the scene's values.

Prints one line: steps, late steps and skipped ticks (counts and % of the steps), the
largest step, the load average; and one of the step times (`~status`'s step_ms of every step
over the insertion): median, p99.9, max; exit status 0 (a measurement, not a test).
"""
import argparse
import json
import math
import os
import subprocess
import threading

import rospy
import random

from geometry_msgs.msg import PoseStamped, WrenchStamped
from needle_sim.msg import NeedleWaypoint, ParameterEstimate, SimStatus
from needle_sim.srv import PredictInsertion, PredictInsertionRequest


def quaternion_along(d, roll=0.0):
    """(w, x, y, z): the smallest rotation carrying x onto the unit vector d (the pose
    convention: x along the needle), after a roll by `roll` about x."""
    w = 1.0 + d[0]
    q = (w, 0.0, -d[2], d[1]) if w > 1e-9 else (0.0, 0.0, 1.0, 0.0)
    n = math.sqrt(sum(c * c for c in q))
    a = [c / n for c in q]
    r = (math.cos(roll / 2), math.sin(roll / 2), 0.0, 0.0)
    return (a[0] * r[0] - a[1] * r[1] - a[2] * r[2] - a[3] * r[3],
            a[0] * r[1] + a[1] * r[0] + a[2] * r[3] - a[3] * r[2],
            a[0] * r[2] - a[1] * r[3] + a[2] * r[0] + a[3] * r[1],
            a[0] * r[3] + a[1] * r[2] - a[2] * r[1] + a[3] * r[0])


def scene_motions(scene):
    """[(needle, base, unit direction, keyframes [(t, advance, roll)])] and the scene's duration,
    from `needle_sim check SCENE --json` (the loader's reading: extends resolved)."""
    from needle_sim import paths
    out = subprocess.run([paths.tool(), "check", scene, "--json"], check=True, capture_output=True, text=True).stdout
    d = json.loads(out)
    tree = d["scene"]
    trees = tree["needles"] if "needles" in tree else [tree["needle"]]
    motions = []
    for info, n in zip(d["needles"], trees):
        keys, roll = [], 0.0
        for k in n.get("motion", [{"t": 0.0, "advance": 0.0}]):
            roll = k.get("roll", roll)
            keys.append((k["t"], k.get("advance", 0.0), roll))
        motions.append((info["name"], info["base_position"], info["base_direction"], keys))
    return motions, tree["time"]["duration"]


def keyframe_at(keys, t):
    """(advance, roll) at time t: linear between keyframes, held after the last."""
    if t <= keys[0][0]:
        return keys[0][1], keys[0][2]
    for (t0, a0, r0), (t1, a1, r1) in zip(keys, keys[1:]):
        if t <= t1:
            f = (t - t0) / (t1 - t0) if t1 > t0 else 1.0
            return a0 + f * (a1 - a0), r0 + f * (r1 - r0)
    return keys[-1][1], keys[-1][2]


def percentile(v, q):
    """The q-th percentile (0-100) of v by linear interpolation, as numpy's default."""
    v = sorted(v)
    if not v:
        return float("nan")
    x = (len(v) - 1) * q / 100.0
    i = int(math.floor(x))
    return v[i] if i + 1 >= len(v) else v[i] + (x - i) * (v[i + 1] - v[i])


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--node", default="needle_sim")
    ap.add_argument("--needle", default="needle")
    ap.add_argument("--rate", type=float, default=500.0, help="poses per second")
    ap.add_argument("--base", type=float, nargs=3, default=[-0.035, 0.01, 0.01], help="the base at rest [m]")
    ap.add_argument("--direction", type=float, nargs=3, default=[1.0, 0.0, 0.0])
    ap.add_argument("--depth", type=float, default=0.023, help="advance [m]")
    ap.add_argument("--speed", type=float, default=0.01, help="[m/s]")
    ap.add_argument("--hold", type=float, default=0.2, help="[s]")
    ap.add_argument("--frame", default="tissue")
    ap.add_argument("--scene", default="", help="stream every needle of this scene its own motion (see above)")
    ap.add_argument("--status-at-ends", action="store_true",
                    help="read ~status only before and after the insertion (no 1 kHz status stream to the client: "
                         "the largest step is then not seen)")
    ap.add_argument("--predict-steps", type=int, default=0, help="a ~predict request of this many steps during the run")
    ap.add_argument("--predict-dt", type=float, default=0.001, help="its time step [s]")
    ap.add_argument("--subscribe-all", action="store_true",
                    help="subscribe to every topic the node publishes, /tf and /diagnostics (undecoded), as rviz and a "
                         "monitor would: the node builds the outputs only for subscribed topics")
    ap.add_argument("--echo-wrench", type=float, default=0.0, metavar="NOISE",
                    help="send the node's wrench back as a measured one with this noise [N] (0: not)")
    ap.add_argument("--echo-every", type=int, default=10, help="every this many wrench messages (default 10)")
    ap.add_argument("--echo-wait", type=float, default=120.0, help="seconds to wait for the estimate of the whole insertion")
    args = ap.parse_args(rospy.myargv()[1:])
    rospy.init_node("node_deadlines", anonymous=True)
    lock = threading.Lock()
    last = {}

    step_ms = {}  # step -> its time, while recording

    def on_status(m):
        with lock:
            last["m"] = m
            if "record" in last:
                step_ms[m.step] = m.step_ms

    sub = rospy.Subscriber(args.node + "/status", SimStatus, on_status, queue_size=1)
    monitors = []
    estimates = []
    # (Before the undecoded subscriptions: rospy keeps a topic's first type.)
    if args.echo_wrench > 0:
        rng = random.Random(1)
        echo = rospy.Publisher("/%s/%s/measured_wrench" % (args.node, args.needle), WrenchStamped, queue_size=100)
        count = [0]

        def on_wrench(m):
            count[0] += 1
            if count[0] % args.echo_every == 0:
                m.wrench.force.x += rng.gauss(0.0, args.echo_wrench)
                echo.publish(m)

        monitors.append(rospy.Subscriber("/%s/%s/wrench" % (args.node, args.needle), WrenchStamped, on_wrench,
                                         queue_size=100))
        monitors.append(rospy.Subscriber(args.node + "/estimate", ParameterEstimate, lambda m: estimates.append(m)))
    t_in = args.depth / args.speed
    if args.scene:
        motions, total = scene_motions(args.scene)
    else:
        # advance along the direction, hold, withdraw: as keyframes
        motions = [(args.needle, args.base, args.direction,
                    [(0.0, 0.0, 0.0), (t_in, args.depth, 0.0), (t_in + args.hold, args.depth, 0.0),
                     (2 * t_in + args.hold, 0.0, 0.0)])]
        total = 2 * t_in + args.hold
    streams = []
    for name, base, direction, keys in motions:
        n = math.sqrt(sum(c * c for c in direction))
        streams.append((rospy.Publisher("/%s/%s/command_pose" % (args.node, name), PoseStamped, queue_size=10),
                        base, [c / n for c in direction], keys))
    while not rospy.is_shutdown() and "m" not in last:
        rospy.sleep(0.05)
    if args.subscribe_all:  # once the node runs (a DBS scene's pre-step comes before its topics)
        prefix = "/" + args.node.strip("/") + "/"
        for name, _ in rospy.get_published_topics():
            if name.startswith(prefix) or name in ("/tf", "/diagnostics"):
                monitors.append(rospy.Subscriber(name, rospy.AnyMsg, lambda m: None, queue_size=1))
        rospy.loginfo("node_deadlines: subscribed to %d topics", len(monitors))

    def pose_of(stream, t):
        _, base, d, keys = stream
        a, roll = keyframe_at(keys, t)
        p = PoseStamped()
        p.header.stamp = rospy.Time.now()
        p.header.frame_id = args.frame
        p.pose.position.x, p.pose.position.y, p.pose.position.z = [b + a * c for b, c in zip(base, d)]
        p.pose.orientation.w, p.pose.orientation.x, p.pose.orientation.y, p.pose.orientation.z = quaternion_along(d, roll)
        return p

    def pose_at(t):  # the first needle's (the prediction's)
        return pose_of(streams[0], t)

    def publish_all(t):
        for s in streams:
            s[0].publish(pose_of(s, t))

    # The rest pose until the node runs, then the insertion.
    for _ in range(20):
        publish_all(0.0)
        rospy.sleep(0.01)
    with lock:
        m0 = last["m"]
    if args.status_at_ends:
        sub.unregister()
    predicted = {}

    def predict():
        # The base held where it will be 0.2 s in, for N steps (a plan the guard accepts).
        rospy.sleep(0.2)
        req = PredictInsertionRequest()
        req.needle = motions[0][0]
        req.dt = args.predict_dt
        req.trajectory.header.frame_id = args.frame
        w = NeedleWaypoint()
        w.time_from_start = rospy.Duration(args.predict_steps * args.predict_dt)
        w.pose = pose_at(0.2).pose
        req.trajectory.waypoints = [w]
        with lock:
            a = last["m"]
        call = rospy.ServiceProxy(args.node + "/predict", PredictInsertion)
        t = rospy.get_time()
        r = call(req)
        predicted["wall"] = rospy.get_time() - t
        with lock:
            b = last["m"]
        predicted.update(response=r, late=b.late_steps - a.late_steps, skipped=b.skipped_ticks - a.skipped_ticks,
                         steps=b.step - a.step)

    if args.predict_steps > 0:
        rospy.wait_for_service(args.node + "/predict", timeout=10)
        if args.status_at_ends:
            raise SystemExit("node_deadlines: --predict-steps needs the status stream (not --status-at-ends)")
        predictor = threading.Thread(target=predict, daemon=True)
        predictor.start()
    rate = rospy.Rate(args.rate)
    with lock:
        last["record"] = True
    t0 = rospy.Time.now()
    step_max = 0.0
    while not rospy.is_shutdown():
        t = (rospy.Time.now() - t0).to_sec()
        if t > total + 0.2:
            break
        publish_all(t)
        if not args.status_at_ends:
            with lock:
                step_max = max(step_max, last["m"].step_ms)
        rate.sleep()
    if args.predict_steps > 0:
        # The robot holds its last pose until the prediction is answered (the node holds the
        # needle without commands), the loop's steps counted on.
        while predictor.is_alive() and not rospy.is_shutdown():
            publish_all(total + 1.0)
            rate.sleep()
    if args.status_at_ends:
        last["m"] = rospy.wait_for_message(args.node + "/status", SimStatus)
    with lock:
        m1 = last["m"]
    steps = m1.step - m0.step if m1.step >= m0.step else m1.step
    late = m1.late_steps - m0.late_steps
    skipped = m1.skipped_ticks - m0.skipped_ticks
    load = os.getloadavg()
    print("node_deadlines: %d steps over %.1f s of insertion at %.0f poses/s: %d late (%.2f %%), %d skipped ticks "
          "(%.2f %%), largest step seen %.2f ms, %d commands rejected, load average %.2f %.2f %.2f" % (
              steps, total, args.rate, late, 100.0 * late / max(steps, 1), skipped, 100.0 * skipped / max(steps, 1),
              step_max, m1.rejected_commands - m0.rejected_commands, load[0], load[1], load[2]))
    with lock:
        times = [v for k, v in step_ms.items() if m0.step < k <= m1.step]
    if times:
        print("node_deadlines: step times of %d steps: median %.3f ms, p99.9 %.3f ms, max %.3f ms" % (
            len(times), percentile(times, 50), percentile(times, 99.9), max(times)))
    if args.echo_wrench > 0:
        # The first estimate that used the whole insertion (the estimator lags the loop by its
        # refits' wall time), at most --echo-wait seconds.
        end = rospy.get_time() + args.echo_wait
        while not rospy.is_shutdown() and rospy.get_time() < end and not (estimates and estimates[-1].t >= m1.sim_time - 0.2):
            rospy.sleep(0.1)
        if not estimates:
            print("node_deadlines: no ~estimate (has the node ~assimilation/keys and ~assimilation/wrench_noise?)")
        else:
            e = estimates[-1]
            print("node_deadlines: %d estimates from the echoed wrench (noise %g N); the last at t = %.3f s (%.2f s of "
                  "wall time, %d samples, %s): %s" % (
                      len(estimates), args.echo_wrench, e.t, e.wall_s, e.samples,
                      "consistent" if e.consistent else "INCONSISTENT",
                      ", ".join("%s = %.6g +- %.2g" % (k, v, s) for k, v, s in zip(e.keys, e.values, e.std))))
    if args.predict_steps > 0:
        if "response" not in predicted:
            print("node_deadlines: the prediction had not returned when the insertion ended")
        else:
            r = predicted["response"]
            print("node_deadlines: a prediction of %d steps at %g s: %.2f s wall, %s; meanwhile %d live steps, %d late "
                  "(%.2f %%), %d skipped ticks" % (
                      args.predict_steps, args.predict_dt, predicted["wall"],
                      "predicted" if r.success else "not predicted (%s)" % r.message, predicted["steps"],
                      predicted["late"], 100.0 * predicted["late"] / max(predicted["steps"], 1), predicted["skipped"]))


if __name__ == "__main__":
    main()

#!/usr/bin/python3
"""The launch files as a user runs them one after another, on a master of the test's own:
  - `rosrun needle_sim needle_sim --help` finds the tool in the package's devel space;
  - `roslaunch needle_sim replay.launch` (the shipped bag by default) ends by itself when the
    bag ends, and leaves no /use_sim_time behind;
  - a `roslaunch needle_sim sim.launch` started after it steps on the wall clock.
Run by CTest (launch_sequence) in the package's environment."""
import os
import signal
import socket
import subprocess
import sys
import time
import unittest

import rosgraph


def free_port():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


class LaunchSequence(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.env = dict(os.environ)
        cls.env["ROS_MASTER_URI"] = "http://127.0.0.1:%d" % free_port()
        cls.env["PATH"] = "/usr/bin:" + cls.env.get("PATH", "")
        cls.core = subprocess.Popen(["roscore", "-p", cls.env["ROS_MASTER_URI"].rsplit(":", 1)[1]], env=cls.env,
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        os.environ["ROS_MASTER_URI"] = cls.env["ROS_MASTER_URI"]
        cls.master = rosgraph.Master("/test_launch_sequence")
        for _ in range(200):
            try:
                cls.master.getPid()
                break
            except Exception:
                time.sleep(0.1)

    @classmethod
    def tearDownClass(cls):
        os.killpg(cls.core.pid, signal.SIGINT)
        cls.core.wait(timeout=20)

    def test_1_rosrun_finds_the_tool(self):
        r = subprocess.run(["rosrun", "needle_sim", "needle_sim", "--help"], env=self.env, capture_output=True,
                           text=True, timeout=60)
        self.assertEqual(r.returncode, 0, r.stdout + r.stderr)
        self.assertIn("run", r.stdout)

    def test_2_replay_ends_with_the_bag_and_cleans_up(self):
        t0 = time.time()
        r = subprocess.run(["roslaunch", "needle_sim", "replay.launch"], env=self.env, capture_output=True, text=True,
                           timeout=120)
        took = time.time() - t0
        print("replay.launch ended after %.1f s (exit %d)" % (took, r.returncode), file=sys.stderr)
        self.assertLess(took, 60, "the replay launch did not end with the bag")
        self.assertIn("needle_sim_play", r.stdout + r.stderr)
        self.assertFalse(self.master.hasParam("/use_sim_time"), "replay.launch left /use_sim_time behind")

    def test_3_sim_launch_afterwards_steps(self):
        p = subprocess.Popen(["roslaunch", "needle_sim", "sim.launch"], env=self.env, stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL, start_new_session=True)
        try:
            r = subprocess.run(["rostopic", "echo", "-n", "1", "/needle_sim/status/step"], env=self.env,
                               capture_output=True, text=True, timeout=60)
            time.sleep(1.0)
            r2 = subprocess.run(["rostopic", "echo", "-n", "1", "/needle_sim/status/step"], env=self.env,
                                capture_output=True, text=True, timeout=30)
        finally:
            os.killpg(p.pid, signal.SIGINT)
            p.wait(timeout=30)
        first = int(r.stdout.split()[0])
        second = int(r2.stdout.split()[0])
        self.assertGreater(second, first + 200, "sim.launch after a replay does not step (waiting for /clock?)")


if __name__ == "__main__":
    unittest.main(verbosity=2)

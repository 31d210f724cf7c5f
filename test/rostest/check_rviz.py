#!/usr/bin/python3
"""rostest (rviz.test, run under Xvfb): the shipped rviz config loads and shows the
insertion. rviz is started with config/needle_sim.rviz beside the node (the phantom
insertion scripted by its scene); the test checks that
  - the config parses (an invalid file opens as an empty grey view),
  - rviz subscribes to the displays' topics (what loading the config does),
  - a screenshot taken with the needle inside the tissue is not blank: the needle's grey
    tube, the tissue surface's colours and the background are all there.
The screenshot is kept as ~screenshot (default: the test results folder)."""
import os
import time
import unittest

import rosgraph
import rospy
import rostest
import yaml
from PIL import ImageGrab

from needle_sim.msg import SimStatus

TOPICS = ["/needle_sim/tissue/surface", "/needle_sim/needle/path", "/needle_sim/needle/marker",
          "/needle_sim/target", "/needle_sim/target/markers", "/needle_sim/tissue/error_markers",
          "/needle_sim/tissue/legend"]


class RvizView(unittest.TestCase):
    def test_config_loads_and_shows_the_needle_and_the_tissue(self):
        config = rospy.get_param("~config")
        with open(config) as f:
            cfg = yaml.safe_load(f)
        displays = cfg["Visualization Manager"]["Displays"]
        self.assertGreaterEqual(len(displays), 8)

        master = rosgraph.Master("/check_rviz")
        deadline = time.time() + 60
        missing = TOPICS
        while time.time() < deadline:
            _, subs, _ = master.getSystemState()
            subscribed = {t for t, nodes in subs if "/rviz" in nodes}
            missing = [t for t in TOPICS if t not in subscribed]
            if not missing:
                break
            time.sleep(0.5)
        self.assertEqual(missing, [], "rviz does not subscribe to these: did it load the config?")

        # Wait until the needle is well inside the tissue (the scene inserts 23 mm in 2.3 s,
        # holds 0.2 s, withdraws).
        state = {"t": 0.0, "states": []}

        def on_status(m):
            state["t"] = m.sim_time
            state["states"] = m.insertion_states

        rospy.Subscriber("/needle_sim/status", SimStatus, on_status)
        deadline = time.time() + 60
        while time.time() < deadline and not (state["t"] > 1.7 and "inserted" in state["states"]):
            time.sleep(0.05)
        self.assertIn("inserted", state["states"])
        time.sleep(0.4)  # a few frames of rviz (it draws at 2 fps or more under Xvfb)
        img = ImageGrab.grab(xdisplay=os.environ["DISPLAY"]).convert("RGB")
        out = rospy.get_param("~screenshot", "")
        if out:
            img.save(out)
        w, h = img.size
        small = img.resize((w // 2, h // 2))
        pixels = list(small.getdata())
        colours = len(set(pixels))
        # The needle: light grey (0.85, 0.85, 0.85) tube, shaded by rviz's light.
        grey = sum(1 for r, g, b in pixels if abs(r - g) < 12 and abs(g - b) < 12 and r > 150)
        # The tissue: |u| colours, blue to green to red, seen through at alpha 0.45 over the
        # background (40, 40, 48): blue or green dominant.
        tissue = sum(1 for r, g, b in pixels if (b > r + 25 or g > r + 25) and max(r, g, b) > 60)
        print("screenshot %dx%d: %d colours, needle-grey pixels %d, tissue pixels %d" % (w, h, colours, grey, tissue))
        self.assertGreater(colours, 200, "the screenshot is nearly uniform: rviz shows nothing")
        self.assertGreater(grey, 200, "no needle in the picture")
        self.assertGreater(tissue, 5000, "no tissue surface in the picture")


if __name__ == "__main__":
    rospy.init_node("check_rviz")
    rostest.rosrun("needle_sim", "rviz_view", RvizView)

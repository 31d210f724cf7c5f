"""The shipped example recordings (data/examples/), made by the simulator with known values so
that `needle_sim calibrate` and `needle_sim run --bag` have something to be tried on:

  phantom_insertion_force.csv   t, axial_force: the phantom insertion (8x4x4, 2 ms steps) with
                                cutting force 30 mN and grip 400 Pa, every 5th step, plus
                                Gaussian noise of 0.5 mN (seed 1). axial_force is a force
                                sensor's reading: negative while the tissue resists.
  phantom_insertion_session.bag the shipped commanded poses (test/data/bags/
                                phantom_insertion_commands.bag, needle/command_pose) and the
                                wrench a replay of them with the same values gives on
                                needle/wrench (in needle_base), every 5th step, with the same
                                noise on its x.

    scripts/make_example_records.py [--tool devel/lib/needle_sim/needle_sim]

Fitting either from (15 mN, 150 Pa) should give back about (30 mN, 400 Pa): doc/calibration.md.
"""
import argparse
import csv
import os
import random
import subprocess
import tempfile

from .. import paths

ROOT = paths.source_dir() or paths.share_dir()
OUT = os.path.join(ROOT, "data", "examples")
TRUTH = ["--set", "time.dt=0.002", "--set", "interaction.cutting_force=0.03", "--set", "interaction.grip_pressure=400"]
NOISE, EVERY, SEED = 5e-4, 5, 1


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tool", default=paths.tool())
    a = ap.parse_args()
    scene = os.path.join(ROOT, "config", "scenes", "phantom_insertion_8x4x4.yaml")
    tmp = tempfile.mkdtemp(prefix="examples_")
    # The CSV: the scene's own motion.
    subprocess.run([a.tool, "run", scene, "--out", os.path.join(tmp, "run"), "--quiet"] + TRUTH, check=True,
                   stdout=subprocess.DEVNULL)
    rng = random.Random(SEED)
    with open(os.path.join(tmp, "run", "timeseries.csv")) as f, open(os.path.join(OUT, "phantom_insertion_force.csv"), "w") as o:
        o.write("t,axial_force\n")
        for r in list(csv.DictReader(f))[EVERY - 1::EVERY]:
            o.write("%s,%.9g\n" % (r["t"], float(r["needle_axial_force"]) + rng.gauss(0.0, NOISE)))
    # The bag: the shipped commands replayed, their wrench recorded beside them.
    commands = os.path.join(ROOT, "test", "data", "bags", "phantom_insertion_commands.bag")
    sim_bag = os.path.join(tmp, "sim.bag")
    subprocess.run([a.tool, "run", scene, "--out", os.path.join(tmp, "replay"), "--quiet", "--bag", commands,
                    "--pose-topic", "needle/command_pose", "--out-bag", sim_bag] + TRUTH, check=True,
                   stdout=subprocess.DEVNULL)
    import rosbag
    rng = random.Random(SEED)
    out = rosbag.Bag(os.path.join(OUT, "phantom_insertion_session.bag"), "w")
    try:
        for topic, msg, t in rosbag.Bag(commands).read_messages(["needle/command_pose", "/needle/command_pose"]):
            out.write("needle/command_pose", msg, t)
        wrenches = list(rosbag.Bag(sim_bag).read_messages(["/needle_sim/needle/wrench"]))
        for _, w, t in wrenches[EVERY - 1::EVERY]:
            w.wrench.force.x += rng.gauss(0.0, NOISE)
            out.write("needle/wrench", w, t)
    finally:
        out.close()
    print("wrote", os.path.join(OUT, "phantom_insertion_force.csv"), "and", os.path.join(OUT, "phantom_insertion_session.bag"))
    return 0

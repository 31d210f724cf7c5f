"""Shared by the ensemble tests: where the tool and the script are, a small cheap study."""
import csv
import os
import subprocess
import tempfile

from needle_sim import paths

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SCRIPTS = os.path.join(ROOT, "scripts")
TOOL = paths.tool()
SCRIPT = os.path.join(SCRIPTS, "ensemble.py")
SCENE = os.path.join(ROOT, "config", "scenes", "phantom_insertion_8x4x4.yaml")
# The phantom insertion cut short (0.6 s: the tip is 3 mm into the block; a run takes about
# 0.2 s), a target 2 mm beside the needle's path, gravity given so one of its components can vary.
BASE = ["--set", "time.duration=0.6", "--set", "targets=[{name: T, point: [0.002, 0.01, 0.012]}]",
        "--set", "tissue.gravity=[0,0,0]"]


def out_dir(name):
    root = os.environ.get("NEEDLE_SIM_TEST_OUT") or tempfile.mkdtemp(prefix="needle_sim_ensemble_test_")
    d = os.path.join(root, name)
    subprocess.run(["rm", "-rf", d], check=True)
    return d


def ensemble(args, **kw):
    """The ensemble script with Debian's python (the tool hands over to the same script)."""
    return subprocess.run(["/usr/bin/python3", SCRIPT, "--tool", TOOL] + list(args), capture_output=True, text=True, **kw)


def rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))

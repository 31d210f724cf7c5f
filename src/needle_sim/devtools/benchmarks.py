"""doc/benchmarks.md's tables, measured and written by one program.

    scripts/benchmarks.py --list                  # the benchmarks, what each measures, how long it takes
    scripts/benchmarks.py                         # the quick set, each table into its block
    scripts/benchmarks.py --only soak steer       # some of them
    scripts/benchmarks.py --full                  # and the studies that take hours
    scripts/benchmarks.py --check                 # exit 1 if a block lacks its table, date, commit or commands

Each table sits between '<!-- ID: table -->' and '<!-- end ID -->' (the block the study scripts
write with --write-doc, studies.runs.write_doc_block) and opens with the date, the commit
(`git describe --always --dirty`), the machine and the commands that made it. Run it on an
otherwise idle machine after `bash scripts/test.sh` has built the tool: a table is only as
good as the machine's quiet. The `node_overhead` benchmark launches the ROS node
(`roslaunch needle_sim sim.launch`): source devel/setup.bash first.
"""
import argparse
import csv
import json
import math
import os
import platform
import random
import re
import shlex
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time

from .. import paths
from ..run_outputs import load_rows as rows_of
from ..run_outputs import load_summary as summary
from ..studies.runs import write_doc_block

DOC = "benchmarks.md"
TOOL_SHOWN = "devel/lib/needle_sim/needle_sim"


def root():
    return paths.share_dir()


def run(cmd, timeout=7200):
    """Runs a command (a list; 'T' stands for the tool) from the repository's root: its stdout."""
    full = [paths.tool() if c == "T" else c for c in cmd]
    p = subprocess.run(full, cwd=root(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, timeout=timeout)
    if p.returncode != 0:
        raise RuntimeError("%s: exit %d\n%s" % (" ".join(full), p.returncode, p.stderr[-2000:]))
    return p.stdout


def shown(cmd):
    """The command as the docs show it (the tool by its path from the repository's root); a
    string is shown as it is (a shell line, a comment)."""
    if isinstance(cmd, str):
        return cmd
    return " ".join(TOOL_SHOWN if c == "T" else shlex.quote(c) for c in cmd)


def placeholder(cmd, option, name):
    """The command with `option`'s value (a temporary path) shown as `name`."""
    c = list(cmd)
    c[c.index(option) + 1] = name
    return c


def tables(text):
    """The Markdown tables a command printed (lines starting with '|')."""
    out, keep = [], False
    for line in text.splitlines():
        if line.startswith("|"):
            out.append(line)
            keep = True
        elif keep:
            out.append("")
            keep = False
    return "\n".join(out).strip() + "\n"


def printed_table(cmd):
    return lambda: (tables(run(cmd)), [cmd])


def ms3(s):
    """'median / p99.9 / max' of a summary's step_ms."""
    return "%.3g / %.3g / %.3g" % (s["median"], s["p999"], s["max"])


# --- benchmarks that need more than the tool's own table --------------------------------

def element_step():
    """The locking-free default element against the paper's at equal DOFs: the phantom
    insertion's grids (bench) and dbs_coarse at the paper's brain (the sourced one locks the
    paper's element: its shift is refused), two runs of each element in alternation."""
    lines, cmds = [], []
    for el in ("trilinear", "incompatible_modes_bbar"):
        cmd = ["T", "bench", "--scene", "phantom_insertion_8x4x4.yaml", "--cells", "8x4x4", "16x8x8", "--steps", "0",
               "--set", "tissue.element=" + el]
        cmds.append(cmd)
        for line in tables(run(cmd)).splitlines():
            if line.startswith("| 8x4x4") or line.startswith("| 16x8x8"):
                c = [x.strip() for x in line.strip("|").split("|")]
                lines.append("| `%s` | phantom insertion %s | %s | %s / %s / %s | |" % (el, c[0], c[1], c[3], c[4], c[5]))
    dbs = {}
    for rep in range(2):
        for el in ("trilinear", "incompatible_modes_bbar"):
            out = tempfile.mkdtemp(prefix="bench_el_")
            cmd = ["T", "run", "config/scenes/dbs_coarse.yaml", "--out", out, "--quiet", "--set", "tissue.element=" + el,
                   "--set", "tissue.material.young=6000", "--set", "tissue.material.poisson=0.45"]
            run(cmd)
            s = summary(out)
            its = sum(int(r["linear_iterations"]) for r in rows_of(out))
            dbs.setdefault(el, []).append((s["step_ms"], s["dofs"], its))
            if rep == 0:
                cmds.append(placeholder(cmd, "--out", "DIR"))
    for el, runs in dbs.items():
        lines.append("| `%s` | dbs_coarse, paper's brain | %s | %s | %s |" % (
            el, runs[0][1], ", ".join(ms3(r[0]) for r in runs), ", ".join("{:,}".format(r[2]) for r in runs)))
    head = ("| element | scene | DOFs | step ms median / p99.9 / max | CG iterations (run) |\n"
            "|---|---|---|---|---|\n")
    return head + "\n".join(lines) + "\n", cmds


def dbs_prestep():
    """The brain-shift pre-step on the adaptive and the fine DBS grids: three loads each."""
    rows, cmds = [], []
    for scene in ("dbs_adaptive", "dbs_fine"):
        ms, out = [], tempfile.mkdtemp(prefix="bench_dbs_")
        cmd = ["T", "run", "config/scenes/%s.yaml" % scene, "--out", out, "--quiet", "--set", "time.duration=0.01"]
        cmds.append(placeholder(cmd, "--out", "DIR"))
        for _ in range(3):
            run(cmd)
            s = summary(out)
            ms.append(s["brain_shift"]["ms"])
        b = s["brain_shift"]
        rows.append("| %s | {:,} | %d | %d | %.0f / %.0f / %.0f | %.6g |".format(b["dofs"]) % (
            scene, b["factorizations"], b["newton_iterations"], min(ms), statistics.median(ms), max(ms), b["load_scale"]))
    head = ("| scene | DOFs (final grid) | factorisations | Newton steps | pre-step ms min / median / max | load scale |\n"
            "|---|---|---|---|---|---|\n")
    return head + "\n".join(rows) + "\n", cmds


def constraint_solve():
    """The block active-set solve against the paper's projected Gauss-Seidel, every step."""
    cases = [("phantom 8×4×4 (E = 10 MPa)", "phantom_insertion_8x4x4", []),
             ("phantom, E = 6 kPa (brain-like)", "phantom_insertion_8x4x4", ["--set", "tissue.material.young=6000"]),
             ("phantom, grip 500 Pa", "phantom_insertion_8x4x4", ["--set", "interaction.grip_pressure=500"]),
             ("`dbs_adaptive`", "dbs_adaptive", [])]
    rows, cmds = [], []
    for label, scene, extra in cases:
        for method, name in (("block", "block"), ("gauss_seidel", "Gauss–Seidel")):
            out = tempfile.mkdtemp(prefix="bench_cs_")
            cmd = ["T", "run", "config/scenes/%s.yaml" % scene, "--out", out, "--quiet",
                   "--set", "interaction.solver.method=" + method] + extra
            run(cmd)
            s = summary(out)
            it = s["interaction"]
            c = it["constraint_ms"]
            rows.append("| %s | %s | {:,} | %s | %s | %d | %.2g |".format(s["steps"]) % (
                label if method == "block" else "", name, ms3(s["step_ms"]), ms3(c), it["unconverged_steps"],
                it["constraint_residual_max"]))
            cmds.append(placeholder(cmd, "--out", "DIR"))
    head = ("| scene | solver | steps | step ms median / p99.9 / max | constraint ms median / p99.9 / max "
            "| unconverged steps | largest residual |\n|---|---|---|---|---|---|---|\n")
    return head + "\n".join(rows) + "\n", cmds


def target_error():
    """The adaptive phantom with a target's goal-oriented error bound every 20 steps (its own
    phase), and the copy of the simulation the node's estimate thread takes; two runs."""
    rows, cmds = [], []
    for rep in range(2):
        out = tempfile.mkdtemp(prefix="bench_goal_")
        cmd = ["T", "bench", "--scene", "phantom_insertion_adaptive.yaml", "--steps", "0", "--target-error-every", "20",
               "--target", "0.022", "0.01", "0.01", "--json", os.path.join(out, "b.json")]
        run(cmd)
        with open(os.path.join(out, "b.json")) as f:
            j = json.load(f)
        g = j["target_error_ms"]
        rows.append("| %d | %s | %d | %.3g / %.3g | %.1f %% | %.3g / %.3g |" % (
            rep + 1, ms3(j["step_ms"]), g["passes"], g["median"], g["max"], 100 * g["share"], g["copy_median"],
            g["copy_max"]))
        if rep == 0:
            cmds.append(placeholder(cmd, "--json", "FILE"))
    head = ("| run | step ms median / p99.9 / max | estimates | estimate ms median / max | share of the run "
            "(steps + estimates) | copy ms median / max |\n"
            "|---|---|---|---|---|---|\n")
    return head + "\n".join(rows) + "\n", cmds


def prediction():
    """A 10 s plan predicted on a copy of the adaptive phantom, five times."""
    out = tempfile.mkdtemp(prefix="bench_predict_")
    cmd = ["T", "predict", "config/scenes/phantom_insertion_adaptive.yaml", "--duration", "10", "--advance", "0.02",
           "--dt", "0.01", "--target", "0.02", "0.01", "0.01", "--repeat", "5", "--compare",
           "--json", os.path.join(out, "p.json")]
    run(cmd)
    with open(os.path.join(out, "p.json")) as f:
        j = json.load(f)
    c = j.get("compare") or {}
    table = ("| scene | simulated | dt | steps | max DOFs | total median ms | copy median ms | run median ms "
             "| faster than real time | against the scene's dt: tip / target / force |\n"
             "|---|---|---|---|---|---|---|---|---|---|\n"
             "| phantom_insertion_adaptive | %g s | %g s | %d | {:,} | %.1f | %.2f | %.1f | %.0f× | %.2g m / %.2g m / %.2g N |\n".format(
                 j["max_dofs"]) % (j["duration"], j["dt"], j["steps"], j["total_ms_median"], j["copy_ms_median"],
                                   j["run_ms_median"], 1e3 * j["duration"] / j["total_ms_median"],
                                   c.get("tip_m", float("nan")), c.get("target_m", float("nan")),
                                   c.get("force_n", float("nan"))))
    return table, [placeholder(cmd, "--json", "FILE")]


def holder_wrench():
    """dbs_coarse's holder force between its 10 ms steps (run --wrench-rate 1000) against a 1 ms run."""
    runs, cmds = {}, []
    for dt in ("0.01", "0.001"):
        out = tempfile.mkdtemp(prefix="bench_wrench_")
        cmd = ["T", "run", "config/scenes/dbs_coarse.yaml", "--out", out, "--quiet", "--set", "time.duration=9",
               "--set", "time.dt=" + dt] + (["--wrench-rate", "1000"] if dt == "0.01" else [])
        run(cmd)
        rows = rows_of(out)
        runs[dt] = {"t": [float(r["t"]) for r in rows], "state": [r["cannula_state"] for r in rows],
                    "axial": [float(r["cannula_axial_force"]) for r in rows],
                    "f": [tuple(float(r["cannula_holder_f" + c]) for c in "xyz") for r in rows]}
        if dt == "0.01":
            with open(os.path.join(out, "wrench.csv")) as f:
                runs[dt]["wrench"] = [(float(r["t"]), r["between"] == "1",
                                       tuple(float(r["cannula_f" + c]) for c in "xyz")) for r in csv.DictReader(f)]
        cmds.append(placeholder(cmd, "--out", "DIR"))
    fine = runs["0.001"]
    at_ms = {round(t * 1e3): f for t, f in zip(fine["t"], fine["f"])}  # the 1 ms run's force by millisecond
    # Per window of time, each millisecond between the 10 ms steps: the wrench.csv row (the
    # step's model: extrapolated from the base's motion) and the last step's force held,
    # against the 1 ms run; and the 10 ms steps themselves.
    windows = [(1.5, 3.0), (3.0, 4.5), (4.5, 6.0), (6.0, 7.3), (7.3, 8.0), (8.0, 8.5), (8.5, 9.0)]
    held, extrapolated, at_steps = ({w: [] for w in windows} for _ in range(3))
    last = None
    for t, between, f in runs["0.01"]["wrench"]:
        if not between:
            last = f
        w = next((w for w in windows if w[0] < t <= w[1] + 1e-9), None)
        ref = at_ms.get(round(t * 1e3))
        if w is None or ref is None:
            continue
        if between:
            held[w].append(math.dist(ref, last))
            extrapolated[w].append(math.dist(ref, f))
        else:
            at_steps[w].append(math.dist(ref, f))

    def first(run, what):
        return next((t for t, s in zip(run["t"], run["state"]) if s == what), float("nan"))

    def rms(v):
        return math.sqrt(sum(x * x for x in v) / len(v))

    def axial_range(w):  # the 1 ms run's axial force on the holder at the window's ends
        return "%.0f to %.0f" % tuple(1e3 * next(a for t, a in zip(fine["t"], fine["axial"]) if t >= x - 1e-9)
                                      for x in w)

    table = ("Punctured at %.3f s (10 ms) and %.3f s (1 ms).\n\n"
             "| t [s] | axial force, 1 ms run [mN] | 10 ms run at its steps: RMS / max [mN] "
             "| held between steps: RMS / max [mN] | wrench.csv between steps: RMS / max [mN] |\n"
             "|---|---|---|---|---|\n") % (first(runs["0.01"], "punctured"), first(fine, "punctured"))
    for w in windows:
        table += "| %.1f-%.1f | %s | %.1f / %.1f | %.1f / %.1f | %.1f / %.1f |\n" % (
            w[0], w[1], axial_range(w), 1e3 * rms(at_steps[w]), 1e3 * max(at_steps[w]),
            1e3 * rms(held[w]), 1e3 * max(held[w]), 1e3 * rms(extrapolated[w]), 1e3 * max(extrapolated[w]))
    return table, cmds

def gel_demo():
    """The gel steering demo (bevel tip, adaptive, 5 ms steps), three runs."""
    rows, cmds = [], []
    for rep in range(3):
        out = tempfile.mkdtemp(prefix="bench_gel_")
        cmd = ["T", "run", "config/scenes/gel_bevel_steering.yaml", "--out", out, "--quiet"]
        t0 = time.monotonic()
        run(cmd)
        wall = time.monotonic() - t0
        s, r = summary(out), rows_of(out)
        cg = statistics.mean(float(x["linear_iterations"]) for x in r)
        rows.append("| %d | %d | %s | %.1f | %.2f |" % (rep + 1, s["steps"], ms3(s["step_ms"]), wall, cg))
        if rep == 0:
            cmds.append(placeholder(cmd, "--out", "DIR"))
    head = ("| run | steps | step ms median / p99.9 / max | wall s (2.8 s simulated) | CG iterations a step |\n"
            "|---|---|---|---|---|\n")
    return head + "\n".join(rows) + "\n", cmds


def _distance_to_path(p, path):
    """The distance of point p from the polyline path (lists of 3 floats)."""
    best = float("inf")
    for a, b in zip(path[:-1], path[1:]):
        ab = [b[i] - a[i] for i in range(3)]
        L2 = sum(c * c for c in ab)
        t = 0.0 if L2 == 0 else max(0.0, min(1.0, sum((p[i] - a[i]) * ab[i] for i in range(3)) / L2))
        best = min(best, math.dist(p, [a[i] + t * ab[i] for i in range(3)]))
    return best


def gel_mesh():
    """The gel demo's cut path on uniform grids and on its adaptive mesh, against a 2 mm grid
    (30x15x15): the adaptivity study's method (the same run on meshes of one family) for the
    choice of the shipped mesh."""
    scene = "config/scenes/gel_bevel_steering.yaml"
    uniform = ["--set", "adaptivity.max_level=0"]  # the scene without refinement: its grid as given
    cases = [("30×15×15 (reference)", uniform + ["--set", "tissue.grid.cells=[30,15,15]"]),
             ("40×20×20", uniform + ["--set", "tissue.grid.cells=[40,20,20]"]),
             ("20×10×10", uniform + ["--set", "tissue.grid.cells=[20,10,10]"]),
             ("10×5×5", uniform),
             ("adaptive 10×5×5 + 1 level (shipped)", [])]
    results, cmds = [], []
    for name, sets in cases:
        out = tempfile.mkdtemp(prefix="bench_gelmesh_")
        cmd = ["T", "run", scene, "--out", out, "--quiet"] + sets
        run(cmd)
        cmds.append(placeholder(cmd, "--out", "DIR"))
        s, r = summary(out), rows_of(out)
        results.append((name, s, max(int(float(x["dofs"])) for x in r)))
    ref = results[0][1]["needles"]["needle"]["cut_path"]
    rows = []
    for name, s, dofs in results:
        path = s["needles"]["needle"]["cut_path"]
        far = max(_distance_to_path(p, ref) for p in path)
        end = math.dist(path[-1], ref[-1])
        bend = max(p[1] for p in path) - 0.015
        plane = max(abs(p[2] - 0.015) for p in path)
        rows.append("| %s | {:,} | %s | %.3f | %.3f | %.2f | %.3f |".format(dofs) % (
            name, ms3(s["step_ms"]), 1e3 * far, 1e3 * end, 1e3 * bend, 1e3 * plane))
    head = ("| mesh | DOFs (max) | step ms median / p99.9 / max (back to back) | path's largest distance from "
            "30×15×15's, mm | end point's, mm | bend (largest y offset), mm | out of plane (largest \\|z − 15 mm\\|), mm |\n"
            "|---|---|---|---|---|---|---|\n")
    return head + "\n".join(rows) + "\n", cmds


PREFLIGHT_SCENES = ["phantom_insertion_adaptive.yaml", "dbs_coarse.yaml", "dbs_adaptive.yaml", "dbs_goal.yaml",
                    "gel_bevel_steering.yaml", "phantom_insertion_32x16x16.yaml", "dbs_fine.yaml"]


def preflight():
    """The pre-flight of every scene meant for a live loop, and of two reference meshes:
    `needle_sim check SCENE` (the node says the same at its start)."""
    rows = []
    for scene in PREFLIGHT_SCENES:
        cmd = ["T", "check", scene, "--json", "--preflight", "3"]
        p = json.loads(run(cmd))["preflight"]
        rows.append("| %s | %g | %d of %d | %.3g s | {:,} | %.3g | %.3g | %.3g | %d (%.1f %%) | %s | %.2f× |".format(
            p["max_dofs"]) % (scene[:-5], 1e3 * p["dt"], p["steps"], p["scene_steps"], p["t_end"], p["step_median_ms"],
                              p["step_p999_ms"], p["step_max_ms"], p["over_dt"], 100.0 * p["over_dt"] / max(1, p["steps"]),
                              "keeps real time" if p["keeps_real_time"] else "**will not**", p["margin"]))
    head = ("| scene | dt ms | steps timed | to t | DOFs max | step median ms | p99.9 ms | max ms | over dt | verdict "
            "| margin (dt / p99.9) |\n|---|---|---|---|---|---|---|---|---|---|---|\n")
    return head + "\n".join(rows) + "\n", ["for s in %s; do %s check $s --preflight 3; done" % (
        " ".join(s[:-5] for s in PREFLIGHT_SCENES), TOOL_SHOWN)]


def steer():
    """The gel demo's roll-flip plan to a target 5 mm off the axis at 40 mm, predictions at the
    scene's 5 ms (at 10 ms they depart from the live run on the adaptive mesh: 0.36 mm)."""
    out = tempfile.mkdtemp(prefix="bench_steer_")
    cmd = ["T", "steer", "config/scenes/gel_bevel_steering.yaml", "--target", "0.040", "0.020", "0.015", "--speed",
           "0.02", "--json", os.path.join(out, "s.json")]
    t0 = time.monotonic()
    printed = run(cmd)
    wall = time.monotonic() - t0
    with open(os.path.join(out, "s.json")) as f:
        j = json.load(f)
    head = [line for line in printed.splitlines() if line.startswith(("steer:", "plan:", "live:"))]
    m = re.search(r"in ([0-9.]+) s", head[0]) if head else None
    live = next((line for line in head if line.startswith("live:")), "")
    lm = re.search(r"([0-9.]+) mm from the target, ([0-9.]+) mm from the prediction", live)
    table = ("| predictions | steps each | planning s | flip depth mm | predicted tip–target mm | live tip–target mm "
             "| live–predicted mm | wall s (with the live run) |\n|---|---|---|---|---|---|---|---|\n"
             "| %d | %s | %s | %.1f | %.3f | %s | %s | %.1f |\n" % (
                 len(j["iterations"]), " + ".join(str(i["steps_run"]) for i in j["iterations"]),
                 m.group(1) if m else "–", 1e3 * j["flip_depth"], 1e3 * j["iterations"][-1]["distance"],
                 lm.group(1) if lm else "not run", lm.group(2) if lm else "–", wall))
    return table, [placeholder(cmd, "--json", "FILE")]


def calibration():
    """A synthetic record (cutting 30 mN, grip 400 Pa, 0.5 mN of noise, every 5th 2 ms step of
    the 8x4x4 phantom insertion) fitted from (15 mN, 150 Pa)."""
    out = tempfile.mkdtemp(prefix="bench_cal_")
    truth = ["--set", "time.dt=0.002", "--set", "interaction.cutting_force=0.03", "--set",
             "interaction.grip_pressure=400"]
    make = ["T", "run", "config/scenes/phantom_insertion_8x4x4.yaml", "--out", os.path.join(out, "truth"),
            "--quiet"] + truth
    run(make)
    rng = random.Random(1)
    with open(os.path.join(out, "force.csv"), "w") as f:
        f.write("t,axial_force\n")
        for r in rows_of(os.path.join(out, "truth"))[4::5]:
            f.write("%s,%.9g\n" % (r["t"], float(r["needle_axial_force"]) + rng.gauss(0.0, 5e-4)))
    cal = ["T", "calibrate", "config/scenes/phantom_insertion_8x4x4.yaml", "--set", "time.dt=0.002", "--data",
           os.path.join(out, "force.csv"), "--fit", "interaction.cutting_force,interaction.grip_pressure", "--start",
           "interaction.cutting_force=0.015", "--start", "interaction.grip_pressure=150", "--out",
           os.path.join(out, "fit"), "--no-plot", "--quiet"]
    run(cal)
    with open(os.path.join(out, "fit", "calibration.json")) as f:
        j = json.load(f)
    p = j["parameters"]
    c, g = p["interaction.cutting_force"], p["interaction.grip_pressure"]
    table = ("| parameter | truth | start | fitted | standard error |\n|---|---|---|---|---|\n"
             "| interaction.cutting_force [N] | 0.03 | 0.015 | %.6g | %.2g |\n"
             "| interaction.grip_pressure [Pa] | 400 | 150 | %.5g | %.2g |\n\n"
             "| RMS residual mN (noise 0.5) | evaluations | + Jacobian | wall s |\n|---|---|---|---|\n"
             "| %.3f | %d | %d | %.1f |\n" % (
                 c["value"], c["std_error"] or float("nan"), g["value"], g["std_error"] or float("nan"),
                 1e3 * j["rms_residual_n"], j["evaluations"], j["jacobian_evaluations"], j["wall_s"]))
    note = "# DIR/force.csv: t and the truth's needle_axial_force every 5th step + N(0, 0.5 mN), seed 1"
    return table, [placeholder(make, "--out", "DIR/truth"), note,
                   placeholder(placeholder(cal, "--data", "DIR/force.csv"), "--out", "DIR/fit")]


def node_overhead():
    """The ROS node's outputs against its core step: sim.launch's phantom, every output
    subscribed, 4 s from the start; two launches."""
    rows = []
    for rep in range(2):
        launch = subprocess.Popen(["roslaunch", "needle_sim", "sim.launch"], cwd=root(), stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL, start_new_session=True)
        try:
            time.sleep(3.0)  # roscore, the node, its scene
            text = run(["/usr/bin/python3", "scripts/node_overhead.py", "--seconds", "4"], timeout=120)
        finally:
            os.killpg(launch.pid, signal.SIGINT)
            launch.wait(timeout=60)
        m = re.search(r"core step median ([0-9.]+) ms, publish median ([0-9.]+) ms, publish p95 ([0-9.]+) ms, "
                      r"overhead \(sum publish / sum step\) ([0-9.]+) %", text)
        o = re.search(r"output thread ([0-9.]+) ms per step \(([0-9.]+) %", text)
        if not m:
            raise RuntimeError("node_overhead.py printed no figures:\n" + text)
        rows.append("| %d | %s | %s | %s | %s %% | %s |" % (rep + 1, m.group(1), m.group(2), m.group(3), m.group(4),
                                                          "%s ms (%s %% of a step)" % o.groups() if o else "–"))
    head = ("| launch | core step median ms | publish median ms | publish p95 ms | sum of publish / sum of steps "
            "| output thread per step (other core) |\n|---|---|---|---|---|---|\n")
    return head + "\n".join(rows) + "\n", ["roslaunch needle_sim sim.launch &   # then, 3 s later:",
                                             "scripts/node_overhead.py --seconds 4"]


def _deadlines_beside_launch(launch_args, client_args, timeout=180):
    """scripts/node_deadlines.py's output against a `roslaunch needle_sim sim.launch` of its own
    (4 s to start: roscore, the node, its scene), and the figures of its first line."""
    launch = subprocess.Popen(["roslaunch", "needle_sim", "sim.launch"] + launch_args, cwd=root(),
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        time.sleep(4.0)
        text = run(["/usr/bin/python3", "scripts/node_deadlines.py", "--rate", "500"] + client_args, timeout=timeout)
    finally:
        os.killpg(launch.pid, signal.SIGINT)
        launch.wait(timeout=60)
    m = re.search(r"(\d+) steps over .* (\d+) late \(([0-9.]+) %\), (\d+) skipped ticks .* largest step seen "
                  r"([0-9.]+) ms", text)
    if not m:
        raise RuntimeError("node_deadlines.py printed no figures:\n" + text)
    return text, m


# The shipped scenes meant for a live loop (#40): the node's criteria are those of its pre-flight.
LIVE_SCENES = ["phantom_insertion_adaptive", "dbs_coarse", "dbs_adaptive", "dbs_goal", "gel_bevel_steering"]


def node_scenes():
    """The node on each live scene by bare name, a 500 Hz client streaming every needle the
    scene's own motion, every output subscribed: late steps, skipped ticks, step times. Two
    launches each: on a shared two-core machine the share of late steps varies from run to run."""
    rows = []
    for name, launch in ((n, k) for n in LIVE_SCENES for k in (1, 2)):
        dt = json.loads(run([paths.tool(), "check", name, "--json"]))["scene"]["time"]["dt"]
        text, m = _deadlines_beside_launch(["scene:=" + name, "command_source:=topic"],
                                           ["--subscribe-all", "--scene", name], timeout=300)
        t = re.search(r"step times of (\d+) steps: median ([0-9.]+) ms, p99.9 ([0-9.]+) ms, max ([0-9.]+) ms", text)
        if not t:
            raise RuntimeError("node_deadlines.py printed no step times:\n" + text)
        steps, late, skipped, p999 = int(m.group(1)), int(m.group(2)), int(m.group(4)), float(t.group(3))
        keeps = late < 0.01 * steps and p999 < 1e3 * dt and skipped == 0
        rows.append("| %s | %d | %g | %d | %s (%s %%) | %s | %s | %s | %s | %s |" % (
            name, launch, 1e3 * dt, steps, m.group(2), m.group(3), m.group(4), t.group(2), t.group(3), t.group(4),
            "yes" if keeps else "**no**"))
    head = ("| scene | launch | dt ms | steps | late steps | skipped ticks | step median ms | p99.9 ms | max ms "
            "| real time (< 1 % late, p99.9 < dt, no skipped tick) |\n|---|---|---|---|---|---|---|---|---|---|\n")
    return head + "\n".join(rows) + "\n", [
        "for s in %s; do   # twice each" % " ".join(LIVE_SCENES),
        "  roslaunch needle_sim sim.launch scene:=$s command_source:=topic &",
        "  scripts/node_deadlines.py --rate 500 --subscribe-all --scene $s   # 4 s later",
        "  kill -INT %1; wait; done"]


def node_prediction():
    """The node's live loop with and without a long ~predict beside it: the adaptive phantom,
    500 Hz poses, a 99,000-step prediction 0.2 s in (stopped by ~predict_max_wall, 5 s)."""
    rows = []
    scene = os.path.join(root(), "config/scenes/phantom_insertion_adaptive.yaml")
    for label, extra in (("none", []), ("99,000 steps at 1 ms", ["--predict-steps", "99000"])):
        text, m = _deadlines_beside_launch(["scene:=" + scene, "command_source:=topic"], extra)
        p = re.search(r"prediction of \d+ steps at [0-9.]+ s: ([0-9.]+) s wall, (.*); meanwhile (\d+) live steps, "
                      r"(\d+) late \(([0-9.]+) %\), (\d+) skipped", text)
        pred = ("%s s, %s; %s late of %s (%s %%), %s skipped" % (
            p.group(1), "predicted" if p.group(2) == "predicted" else "stopped by ~predict_max_wall", p.group(4),
            p.group(3), p.group(5), p.group(6)) if p else "–")
        rows.append("| %s | %s | %s (%s %%) | %s | %s | %s |" % (label, m.group(1), m.group(2), m.group(3), m.group(4),
                                                                m.group(5), pred))
    head = ("| prediction beside the loop | steps | late steps | skipped ticks | largest step seen ms "
            "| the prediction: wall, outcome; the loop meanwhile |\n|---|---|---|---|---|---|\n")
    return head + "\n".join(rows) + "\n", [
        "roslaunch needle_sim sim.launch scene:=$PWD/config/scenes/phantom_insertion_adaptive.yaml command_source:=topic &",
        "scripts/node_deadlines.py --rate 500 [--predict-steps 99000]   # 4 s later; a launch each"]


def node_assimilation():
    """The node's live loop with and without the online estimate beside it: the phantom
    (8x4x4, 1 ms), 500 Hz poses, every subscribed, the node's own wrench sent back every 10 ms
    with 0.5 mN of noise as a measured one; with ~assimilation/keys the cutting force refitted
    every 0.5 s (its estimate from the node's own force must be the scene's 20 mN)."""
    rows = []
    scene = os.path.join(root(), "config/scenes/phantom_insertion_8x4x4.yaml")
    for label, extra in (("off", []), ("on: interaction.cutting_force", ["assimilate:=interaction.cutting_force"])):
        text, m = _deadlines_beside_launch(
            ["scene:=" + scene, "command_source:=topic"] + extra,
            ["--subscribe-all", "--echo-wrench", "0.0005", "--echo-wait", "180" if extra else "0"], timeout=400)
        e = re.search(r"(\d+) estimates from the echoed wrench .* the last at t = ([0-9.]+) s \(([0-9.]+) s of wall time, "
                      r"(\d+) samples, (\w+)\): (.*)", text)
        est = ("%s estimates; the last (t = %s s, %s samples, %s s of wall time, %s): %s" % (
            e.group(1), e.group(2), e.group(4), e.group(3), e.group(5), e.group(6)) if e else "–")
        if extra and not e:
            raise RuntimeError("no estimate from the node:\n" + text)
        rows.append("| %s | %s | %s (%s %%) | %s | %s | %s |" % (label, m.group(1), m.group(2), m.group(3), m.group(4),
                                                                m.group(5), est))
    head = ("| online estimate | steps | late steps | skipped ticks | largest step seen ms | its estimate |\n"
            "|---|---|---|---|---|---|\n")
    return head + "\n".join(rows) + "\n", [
        "roslaunch needle_sim sim.launch command_source:=topic [assimilate:=interaction.cutting_force] &",
        "scripts/node_deadlines.py --rate 500 --subscribe-all --echo-wrench 0.0005   # 4 s later; a launch each"]


def stability_sweep():
    """The whole stability sweep (one parameter at a time across its range); its map into doc/."""
    out = "results/stability"
    cmd = ["/usr/bin/python3", "scripts/stability_sweep.py", "--out", out]
    run(cmd)
    with open(os.path.join(root(), out, "sweep.md"), encoding="utf-8") as f:
        table = tables(f.read())
    shutil.copy(os.path.join(root(), out, "stability_map.png"), os.path.join(root(), "doc", "stability_map.png"))
    return table, [cmd]


CI_LOG = {}  # --ci-log FILE --ci-rev REV: the phase times of a .ci/run already made


def ci():
    """.ci/run on a clean clone of the commit checked out (what CI runs): its phase times; or
    those a clean clone's .ci/run printed to the log given (--ci-log, with its commit)."""
    if CI_LOG:
        rev, text, code, clone = CI_LOG["rev"], open(CI_LOG["log"]).read(), 0, CI_LOG["log"]
    else:
        work = tempfile.mkdtemp(prefix="bench_ci_")
        clone = os.path.join(work, "needle_sim")
        subprocess.run(["git", "clone", "-q", root(), clone], check=True)
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=clone, stdout=subprocess.PIPE,
                             text=True).stdout.strip()
        p = subprocess.run(["bash", ".ci/run"], cwd=clone, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                           text=True, timeout=3 * 3600)
        text, code = p.stderr, p.returncode
    tail = text.split("=== .ci/run phase times ===")[-1]
    rows = ["| %s | %s |" % (m.group(2), m.group(1)) for m in re.finditer(r"^\s*(\d+) s  (.+)$", tail, re.M)]
    if code != 0 or not rows:
        raise RuntimeError(".ci/run failed (exit %d) in %s:\n%s" % (code, clone, text[-3000:]))
    if not CI_LOG:
        shutil.rmtree(work, ignore_errors=True)
    table = "| phase (clean clone of %s) | seconds |\n|---|---|\n%s\n" % (rev, "\n".join(rows))
    return table, ["git clone -q . DIR && cd DIR && bash .ci/run"]


def study(script, args, minutes):
    """A study script that writes its own blocks (--write-doc): run for --full only."""
    cmd = ["/usr/bin/python3", "scripts/%s" % script] + list(args) + ["--write-doc"]

    def measure():
        subprocess.run(cmd, cwd=root(), check=True, timeout=minutes * 60 * 3)
        return None, [cmd]
    return measure


BENCHMARKS = [
    # id, what, minutes on an idle 2-core machine, --full only, how
    ("phantom_step", "the paper's phantom under gravity, three grids: the stale-factor PCG against a fresh factor "
     "every step", 1, False, printed_table(["T", "bench", "--compare-direct"])),
    ("needle_step", "a needle alone in free motion (the beam's step), microseconds",
     1, False, printed_table(["T", "bench", "--scene", "needle_free_motion.yaml", "--steps", "5000"])),
    ("insertion", "the phantom insertion on 8×4×4 and 16×8×8 with a shaft point every 0.4 mm, every step",
     1, False, printed_table(["T", "bench", "--scene", "phantom_insertion_8x4x4.yaml", "--cells", "8x4x4", "16x8x8",
                              "--steps", "0", "--set", "interaction.shaft_spacing=0.0004"])),
    ("element_step", "the default element against the paper's at equal DOFs", 2, False, element_step),
    ("adaptive_phantom", "the adaptive phantom insertion, every step back to back",
     1, False, printed_table(["T", "bench", "--scene", "phantom_insertion_adaptive.yaml", "--steps", "0"])),
    ("adaptive_phantom_paced", "the adaptive phantom insertion paced at its 1 ms (step k starts at k dt)",
     1, False, printed_table(["T", "bench", "--scene", "phantom_insertion_adaptive.yaml", "--steps", "0", "--pace"])),
    ("dbs_paced", "the adaptive DBS scene paced at its 10 ms (after the brain shift)",
     1, False, printed_table(["T", "bench", "--scene", "dbs_adaptive.yaml", "--steps", "0", "--pace"])),
    ("dbs_prestep", "the brain-shift pre-step when a DBS scene loads, three loads each", 1, False, dbs_prestep),
    ("preflight", "the pre-flight (3 s of each scene's motion, paced) of the live scenes and two references",
     2, False, preflight),
    ("constraint_solve", "the block active-set constraint solve against projected Gauss–Seidel, four scenes",
     2, False, constraint_solve),
    ("target_error", "the adaptive phantom with a target's goal-oriented error bound every 20 steps",
     1, False, target_error),
    ("prediction", "a 10 s plan predicted on a copy of the adaptive phantom", 1, False, prediction),
    ("holder_wrench", "dbs_coarse's holder force at its 10 ms step against a 1 ms run, to 9 s", 2, False,
     holder_wrench),
    ("gel_demo", "the bevel-tip gel demo, three runs", 1, False, gel_demo),
    ("gel_mesh", "the gel demo's cut path on four uniform grids and its adaptive mesh", 8, False, gel_mesh),
    ("steer", "a bevel needle's roll-flip plan and its live run", 1, False, steer),
    ("calibration", "calibrate recovering known cutting force and grip from a noisy synthetic record",
     1, False, calibration),
    ("node_overhead", "the ROS node's output cost against its step (launches the node)", 1, False, node_overhead),
    ("node_scenes", "the node on every live scene, a 500 Hz client, every output subscribed (launches the node)", 3,
     False, node_scenes),
    ("node_prediction", "the node's loop with a long ~predict beside it (launches the node)", 1, False,
     node_prediction),
    ("node_assimilation", "the node's loop with and without the online estimate beside it (launches the node)", 5,
     False, node_assimilation),
    ("soak", "a back-and-forth insertion for 22,500 steps: memory and step time per cycle",
     1, False, printed_table(["T", "soak", "config/scenes/phantom_insertion_adaptive.yaml", "--steps", "22500"])),
    ("stability_sweep", "the stability sweep: one parameter at a time across its range", 2, False, stability_sweep),
    ("adaptivity_study", "run time against probe error, adaptive against uniform meshes (writes its block)",
     45, True, study("adaptivity_study.py", ["--out", "results/adaptivity_study"], 45)),
    ("dbs_study", "the DBS scenario on every grid, with its friction sensitivity (writes dbs_study and "
     "dbs_sensitivity; the 4 mm reference runs are reused when present, about 2 h when not)", 150, True,
     study("dbs_study.py", ["--out", "results/dbs_study", "--reuse", "--reference", "--sensitivity", "--jobs", "2"],
           150)),
    ("dbs_reproducibility", "the DBS prediction with only the CG tolerance and the factor's swap lag changed, two "
     "scenes (writes its block)", 8, True, study("reproducibility_study.py", ["--out", "results/reproducibility",
                                                                             "--jobs", "2"], 8)),
    ("assimilation", "twin experiments of run --assimilate: the phantom over 10 seeds and a DBS scene (writes its "
     "block)", 35, True, study("assimilation_study.py", ["--out", "results/assimilation_study", "--dbs"], 35)),
    ("ci", ".ci/run on a clean clone: the phase times", 60, True, ci),
]


def commit():
    try:
        return subprocess.run(["git", "describe", "--always", "--dirty"], cwd=root(), stdout=subprocess.PIPE,
                              text=True).stdout.strip() or "unknown"
    except OSError:
        return "unknown"


def machine():
    cpu = "unknown CPU"
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return "%s, %d cores, %s" % (cpu, os.cpu_count() or 0, platform.platform(terse=True))


def block_re(bid):
    return re.compile(r"<!-- %s: table -->\n(.*?)<!-- end %s -->" % (re.escape(bid), re.escape(bid)), re.S)


def check(path):
    """Every benchmark has its block; each block names its date, commit and command and holds a table."""
    text = open(path, encoding="utf-8").read()
    bad = []
    for bid, _, _, full, _ in BENCHMARKS:
        m = block_re(bid).search(text)
        if not m:
            bad.append("%s (no block)" % bid)
        elif full and not m.group(1).strip():
            continue  # a --full benchmark not measured yet: an empty block
        elif not re.match(r"Made on \d{4}-\d\d-\d\d at \S+ by `[^`]+`", m.group(1)) or "|---" not in m.group(1):
            bad.append("%s (no 'Made on DATE at COMMIT by `COMMAND`' line or no table)" % bid)
    if bad:
        print("%s: %s" % (path, "; ".join(bad)))
        return 1
    print("%s: %d benchmark blocks, each with its date, commit, command and table" % (path, len(BENCHMARKS)))
    return 0


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", nargs="+", metavar="ID")
    ap.add_argument("--full", action="store_true", help="also the studies that take hours")
    ap.add_argument("--list", action="store_true")
    ap.add_argument("--check", action="store_true")
    ap.add_argument("--ci-log", metavar="FILE", help="ci: the phase times from this .ci/run output (stderr) of a "
                                                    "clean clone instead of a run of its own")
    ap.add_argument("--ci-rev", metavar="REV", help="with --ci-log: the commit that run was of")
    a = ap.parse_args()
    if a.ci_log:
        if not a.ci_rev:
            sys.exit("benchmarks.py: --ci-log needs --ci-rev (the commit its clone was of)")
        CI_LOG.update(log=a.ci_log, rev=a.ci_rev)
    path = os.path.join(root(), "doc", DOC)
    known = [b[0] for b in BENCHMARKS]
    if a.list:
        for bid, what, minutes, full, _ in BENCHMARKS:
            print("%-24s %4d min%s  %s" % (bid, minutes, " (--full)" if full else "", what))
        return 0
    if a.check:
        return check(path)
    wanted = a.only or [b[0] for b in BENCHMARKS if a.full or not b[3]]
    unknown = [w for w in wanted if w not in known]
    if unknown:
        sys.exit("benchmarks.py: no benchmark %s (--list)" % ", ".join(unknown))
    if not os.access(paths.tool(), os.X_OK):
        sys.exit("benchmarks.py: no needle_sim tool at %s (build first: bash scripts/test.sh)" % paths.tool())
    # The commit measured: taken once, before the first table makes the page (and the tree) dirty.
    where, rev = machine(), commit()
    for bid, what, minutes, full, how in BENCHMARKS:
        if bid not in wanted:
            continue
        print("benchmarks.py: %s (about %d min) ..." % (bid, minutes), flush=True)
        table, cmds = how()
        if table is None:
            continue  # a study: it wrote its own blocks
        md = "On %s:\n\n```bash\n%s\n```\n\n%s" % (where, "\n".join(shown(c) for c in cmds), table)
        # Written after each: a long run keeps what it measured.
        made_by = "scripts/benchmarks.py --only %s" % bid
        if bid == "ci" and CI_LOG:  # the phase times of a clean clone's .ci/run made before
            made_by += " --ci-log LOG --ci-rev %s" % CI_LOG["rev"]
        write_doc_block(DOC, bid, md, made_by, rev)
    print("benchmarks.py: %s written (commit %s)" % (path, rev))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Behaviour regression for refactors: every shipped scene, before and after.

    scene_regression.py record --tool devel/lib/needle_sim/needle_sim --out /tmp/before [--only NAME ...]
    scene_regression.py compare /tmp/before /tmp/after [--allow FILE:COLUMN ...]

`record` runs every scene of config/scenes (the long ones to a fixed prefix of simulated
time, listed in PREFIX), the target-error runs of the adaptive phantom and the adaptive DBS
scene, a prediction, a steering plan and a bag replay, each into a folder of its own.
`compare` compares two such records: summary.json value by value and every CSV cell by
cell, as text: equal to the last printed digit. Wall times (keys and columns ending in
`ms`, `_s` of timings, shares of the run) and the counts of waits for background threads
(pass_waits, rebuild_waits: how often the stepping thread was ahead of them, which depends
on the machine's load, not on the results) are not compared. `--allow` names columns or
keys whose change is expected (a sign convention), or whose addition or removal is (a column
renamed: the old name and the new one), listed in the report; columns on both sides are
compared by name. Exit status 0 when the records agree, 1 when they do not.
"""
import argparse
import csv
import json
import math
import os
import re
import subprocess
import sys
import time

from .. import paths

ROOT = paths.share_dir()
SCENES = os.path.join(ROOT, "config", "scenes")

# Simulated seconds run of the scenes whose full run is long on a 2-core machine. The prefix
# covers the behaviour a refactor can change: the DBS scenes' brain shift and re-planning,
# the touch, the puncture and the first mesh changes of the insertion.
PREFIX = {
    "dbs_fine": 2.0,
    "phantom_insertion_16x8x8": 2.0,
    "phantom_insertion_32x16x16": 1.0,
}

# Extra runs: (name, arguments after the tool).
def extra_runs():
    s = lambda n: os.path.join(SCENES, n + ".yaml")
    bag = os.path.join(ROOT, "test", "data", "bags", "phantom_insertion_commands.bag")
    return [
        ("te_phantom_insertion_adaptive", ["run", s("phantom_insertion_adaptive"), "--target-error",
                                           "--target-error-every", "10", "--set", "time.duration=2.0", "--set",
                                           "targets=[{name: a, point: [0.02, 0.012, 0.01]}, "
                                           "{name: b, point: [0.03, 0.008, 0.012], radius: 0.0005}]"]),
        ("te_dbs_adaptive", ["run", s("dbs_adaptive"), "--target-error", "--set", "time.duration=2.0"]),
        ("predict_phantom_adaptive", ["predict", s("phantom_insertion_adaptive"), "--at", "0.5", "--duration", "2",
                                      "--advance", "0.01", "--dt", "0.01", "--target", "0.02", "0.01", "0.01",
                                      "--repeat", "1"]),
        ("steer_gel", ["steer", s("gel_bevel_steering"), "--target", "0.040", "0.020", "0.015", "--speed", "0.02",
                       "--dt", "0.01", "--max-predictions", "3"]),
        ("bag_replay", ["run", s("phantom_insertion_8x4x4"), "--bag", bag, "--pose-topic", "needle/command_pose"]),
        # Mesh changes on the stepping thread (the shipped adaptive scenes defer them).
        ("sync_phantom_insertion_adaptive", ["run", s("phantom_insertion_adaptive"), "--set",
                                             "adaptivity.rebuild_delay=0", "--set", "adaptivity.estimate_delay=0"]),
        ("sync_dbs_adaptive", ["run", s("dbs_adaptive"), "--set", "adaptivity.rebuild_delay=0", "--set",
                               "adaptivity.estimate_delay=0", "--set", "time.duration=4"]),
        # A static load step on an adaptive mesh (solve, adapt, solve again).
        ("static_adaptive_cantilever", ["run", s("cantilever_hex8"), "--set",
                                        "adaptivity={theta: 0.5, max_level: 2}"]),
    ]

# Not compared: wall times and scheduling counts (see the docstring).
SKIP_KEY = re.compile(r"(^|_)ms($|_)|_ms$|^ms$|share|_waits$|^pass_waits$|^rebuild_waits$|wall|seconds_wall|"
                      r"compute_time|^seconds$|^plan_s$|elapsed|per_second|realtime|real_time|cpu")


def record(args):
    os.makedirs(args.out, exist_ok=True)
    jobs = []
    for f in sorted(os.listdir(SCENES)):
        if not f.endswith(".yaml"):
            continue
        name = f[:-5]
        cmd = ["run", os.path.join(SCENES, f)]
        if name in PREFIX:
            cmd += ["--set", "time.duration=%g" % PREFIX[name]]
        jobs.append((name, cmd))
    jobs += extra_runs()
    failed = 0
    for name, cmd in jobs:
        if args.only and name not in args.only:
            continue
        out = os.path.join(args.out, name)
        os.makedirs(out, exist_ok=True)
        full = [args.tool] + cmd
        if cmd[0] == "run":
            full += ["--out", out, "--quiet"]
        elif cmd[0] == "predict":
            full += ["--csv", os.path.join(out, "predict.csv"), "--json", os.path.join(out, "predict.json")]
        elif cmd[0] == "steer":
            full += ["--json", os.path.join(out, "steer.json")]
        t0 = time.time()
        p = subprocess.run(full, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        with open(os.path.join(out, "stdout.txt"), "w") as fh:
            fh.write(p.stdout)
        with open(os.path.join(out, "exit_status"), "w") as fh:
            fh.write("%d\n" % p.returncode)
        print("%-34s exit %d  %6.1f s" % (name, p.returncode, time.time() - t0), flush=True)
        failed += p.returncode not in (0, 1)
    return 0


def same_number(a, b):
    return a == b or (isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b))


def compare_json(a, b, path, diffs, allow):
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if SKIP_KEY.search(k):
                continue
            p = path + "." + k if path else k
            if k not in a or k not in b:
                side = "after" if k not in a else "before"
                allowed = any(re.fullmatch(x, p) for x in allow)
                diffs.append("%s%s: only in %s" % ("allowed " if allowed else "", p, side))
                continue
            compare_json(a[k], b[k], p, diffs, allow)
    elif isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            diffs.append("%s: length %d -> %d" % (path, len(a), len(b)))
            return
        for i, (x, y) in enumerate(zip(a, b)):
            compare_json(x, y, "%s[%d]" % (path, i), diffs, allow)
    elif not same_number(a, b):
        if any(re.fullmatch(x, path) for x in allow):
            diffs.append("allowed %s: %r -> %r" % (path, a, b))
        else:
            diffs.append("%s: %r -> %r" % (path, a, b))


def compare_csv(fa, fb, diffs, allow, label):
    with open(fa) as ha, open(fb) as hb:
        ra, rb = list(csv.reader(ha)), list(csv.reader(hb))
    if not ra or not rb:
        if ra != rb:
            diffs.append("%s: one is empty" % label)
        return
    ha, hb = ra[0], rb[0]
    is_allowed = lambda col: any(re.fullmatch(p, label + ":" + col) for p in allow)
    if ha != hb:
        # Columns added or removed: allowed ones are listed, any other is a difference; a
        # column on both sides is compared by name wherever it stands.
        only = [(c, "before") for c in ha if c not in hb] + [(c, "after") for c in hb if c not in ha]
        for col, side in only:
            diffs.append("%s%s: column %s only in %s" % ("allowed " if is_allowed(col) else "", label, col, side))
        common = [c for c in ha if c in hb]
        if [c for c in ha if c in common] != [c for c in hb if c in common]:
            diffs.append("%s: the common columns changed order" % label)
    if len(ra) != len(rb):
        diffs.append("%s: %d -> %d rows" % (label, len(ra) - 1, len(rb) - 1))
    keep = [(i, hb.index(c)) for i, c in enumerate(ha) if c in hb and not SKIP_KEY.search(c)]
    allowed = set()
    for r, (x, y) in enumerate(zip(ra[1:], rb[1:]), start=1):
        for i, j in keep:
            if i < len(x) and j < len(y) and x[i] != y[j]:
                col = ha[i]
                if is_allowed(col):
                    allowed.add(col)
                    continue
                diffs.append("%s row %d (%s=%s) column %s: %s -> %s" % (label, r, ha[0], x[0], col, x[i], y[j]))
                if len(diffs) > 40:
                    return
    for col in sorted(allowed):
        diffs.append("allowed %s:%s changed" % (label, col))


def compare(args):
    names = sorted(set(os.listdir(args.before)) | set(os.listdir(args.after)))
    bad = 0
    for name in names:
        a, b = os.path.join(args.before, name), os.path.join(args.after, name)
        if not (os.path.isdir(a) and os.path.isdir(b)):
            print("%-34s only in %s" % (name, "before" if os.path.isdir(a) else "after"))
            bad += 1
            continue
        diffs = []
        ea, eb = (open(os.path.join(d, "exit_status")).read().strip() for d in (a, b))
        if ea != eb:
            diffs.append("exit status %s -> %s" % (ea, eb))
        for f in sorted(set(os.listdir(a)) | set(os.listdir(b))):
            fa, fb = os.path.join(a, f), os.path.join(b, f)
            if not (os.path.isfile(fa) and os.path.isfile(fb)):
                if f.endswith((".json", ".csv")):
                    diffs.append("%s only in %s" % (f, "before" if os.path.isfile(fa) else "after"))
                continue
            if f.endswith(".json"):
                with open(fa) as ha, open(fb) as hb:
                    compare_json(json.load(ha), json.load(hb), f, diffs, args.allow)
            elif f.endswith(".csv"):
                compare_csv(fa, fb, diffs, args.allow, f)
        real = [d for d in diffs if not d.startswith("allowed")]
        print("%-34s %s" % (name, "same" if not diffs else ("%d differences" % len(real) if real else "same but allowed")))
        for d in diffs[:40]:
            print("    " + d)
        bad += bool(real)
    print("records %s" % ("agree" if not bad else "differ in %d runs" % bad))
    return 1 if bad else 0


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record")
    r.add_argument("--tool", default=paths.tool())
    r.add_argument("--out", required=True)
    r.add_argument("--only", nargs="*")
    c = sub.add_parser("compare")
    c.add_argument("before")
    c.add_argument("after")
    c.add_argument("--allow", nargs="*", default=[], help="regular expressions: FILE:COLUMN or JSON key paths")
    args = ap.parse_args()
    return record(args) if args.cmd == "record" else compare(args)


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/python3
"""The grip pressure's friction per metre, refined (issue #21's verification): the phantom's
straight insertion (2 cm at 1 cm/s, hold, withdrawal) with and without a grip pressure p, on
uniform tissue meshes 8x4x4 and 16x8x8 (and 32x16x16 with --fine), with shaft points every
2, 1 and 0.5 mm of cut path. The slope of the holder's axial force against depth (8-18 mm)
must grow by mu 2 pi r p (Coulomb friction on the pressure on the wall, doc/method.md "Shaft
grip"). The grip's friction is carried by the shaft points, each with the pressure over its
spacing: the force grows in steps of one spacing, and the fitted slope's difference from
mu 2 pi r p is that staircase's, which shrinks with the spacing (the tissue mesh does not
enter a straight insertion's axial friction). test_constraint_solve checks 8x4x4 at 1 mm to
10 %; this script shows the convergence.

    scripts/grip_slope.py --out /tmp/grip            # 12 runs, about 1 min
    scripts/grip_slope.py --out /tmp/grip --fine     # + 32x16x16, about 15 min more
"""
import argparse
import csv
import math
import os
import subprocess
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import package_paths  # noqa: E402


def slope(run_dir, needle="needle"):
    """Least-squares slope of the axial holder force (positive: pushing) against depth."""
    xs, ys = [], []
    with open(os.path.join(run_dir, "timeseries.csv")) as f:
        for r in csv.DictReader(f):
            t = float(r["t"])
            depth = 0.01 * t - 0.003  # the tip enters at t = 0.3 s
            if 0.008 < depth < 0.018:
                fvec = [float(r[f"{needle}_base_f{c}"]) for c in "xyz"]
                dvec = [float(r[f"{needle}_dir_{c}"]) for c in "xyz"]
                xs.append(depth)
                ys.append(sum(a * b for a, b in zip(fvec, dvec)))
    n = len(xs)
    mx, my = sum(xs) / n, sum(ys) / n
    return sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sum((x - mx) ** 2 for x in xs)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--tool", default=None)
    ap.add_argument("--pressure", type=float, default=500.0, help="grip pressure [Pa] (default 500)")
    ap.add_argument("--fine", action="store_true", help="add the 32x16x16 mesh")
    a = ap.parse_args()
    tool = a.tool or package_paths.tool()
    meshes = ["8x4x4", "16x8x8"] + (["32x16x16"] if a.fine else [])
    mu, r = 0.05, 0.001  # the phantom scenes' friction and needle radius
    expected = mu * 2 * math.pi * r * a.pressure
    rows = []
    for m in meshes:
        for sp in (0.002, 0.001, 0.0005):
            s = {}
            for p in (0.0, a.pressure):
                d = os.path.join(a.out, f"{m}_s{sp * 1e3:g}mm_p{int(p)}")
                cmd = [tool, "run", package_paths.scene(f"phantom_insertion_{m}.yaml"), "--out", d,
                       "--set", f"interaction.grip_pressure={p}", "--set", f"interaction.shaft_spacing={sp}",
                       "--set", "time.duration=4.6"]
                print("+", " ".join(cmd), file=sys.stderr)
                subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                s[p] = slope(d)
            # The sign of base_f along the tip direction is fixed by the recorder; the grip's
            # part is the difference of the two runs whatever that sign.
            added = abs(s[a.pressure] - s[0.0])
            rows.append((m, sp, s[0.0], s[a.pressure], added, (added - expected) / expected))
    os.makedirs(a.out, exist_ok=True)
    with open(os.path.join(a.out, "grip_slope.md"), "w") as f:
        f.write(f"grip {a.pressure:g} Pa, mu {mu}, r {r} m: expected added slope {expected:.4f} N/m\n\n")
        f.write("| mesh | shaft spacing [mm] | slope without grip [N/m] | with grip [N/m] | added [N/m] | relative error |\n"
                "|---|---|---|---|---|---|\n")
        for m, sp, s0, s1, add, err in rows:
            f.write(f"| {m} | {sp * 1e3:g} | {s0:.4f} | {s1:.4f} | {add:.4f} | {err:+.2%} |\n")
    print(open(os.path.join(a.out, "grip_slope.md")).read())


if __name__ == "__main__":
    main()

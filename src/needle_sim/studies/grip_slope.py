"""The grip pressure's friction per metre, refined (issue #21's verification): the phantom's
straight insertion (2 cm at 1 cm/s, hold, withdrawal) with and without a grip pressure p, on
uniform tissue meshes 8x4x4 and 16x8x8 (and 32x16x16 with --fine), with shaft points every
2, 1 and 0.5 mm of cut path. The slope against depth (8-18 mm) of the axial force on the
holder (negative while the tissue resists: the slope is negative) must steepen by mu 2 pi r p
(Coulomb friction on the pressure on the wall, doc/method.md "Shaft grip"). The grip's friction is carried by the shaft points, each with the pressure over its
spacing: the force grows in steps of one spacing, and the fitted slope's difference from
mu 2 pi r p is that staircase's, which shrinks with the spacing (the tissue mesh does not
enter a straight insertion's axial friction). test_constraint_solve checks 8x4x4 at 1 mm to
10 %; this script shows the convergence.

    scripts/grip_slope.py --out /tmp/grip            # 12 runs, about 1 min
    scripts/grip_slope.py --out /tmp/grip --fine     # + 32x16x16, about 15 min more
"""
import argparse
import math
import os
import subprocess
import sys

from .. import paths
from ..run_outputs import load_rows, load_summary, names


def slope(run_dir):
    """Least-squares slope against depth of the axial force on the holder (the column
    <needle>_axial_force: negative when the tissue resists, so the slope is negative)."""
    needle = names(load_summary(run_dir), "needles")[0]
    xs, ys = [], []
    for r in load_rows(run_dir):
        t = float(r["t"])
        depth = 0.01 * t - 0.003  # the tip enters at t = 0.3 s
        if 0.008 < depth < 0.018:
            xs.append(depth)
            ys.append(float(r[f"{needle}_axial_force"]))
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
    tool = a.tool or paths.tool()
    meshes = ["8x4x4", "16x8x8"] + (["32x16x16"] if a.fine else [])
    mu, r = 0.05, 0.001  # the phantom scenes' friction and needle radius
    expected = mu * 2 * math.pi * r * a.pressure
    rows = []
    for m in meshes:
        for sp in (0.002, 0.001, 0.0005):
            s = {}
            for p in (0.0, a.pressure):
                d = os.path.join(a.out, f"{m}_s{sp * 1e3:g}mm_p{int(p)}")
                cmd = [tool, "run", paths.scene(f"phantom_insertion_{m}.yaml"), "--out", d,
                       "--set", f"interaction.grip_pressure={p}", "--set", f"interaction.shaft_spacing={sp}",
                       "--set", "time.duration=4.6"]
                print("+", " ".join(cmd), file=sys.stderr)
                subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                s[p] = slope(d)
            # The grip holds the needle back more: the (negative) slope steepens by its part.
            added = s[0.0] - s[a.pressure]
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

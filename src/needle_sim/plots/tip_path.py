"""Plots of a steering run (`needle_sim run` of a scene with a bevel tip): each needle's cut
path from DIR/summary.json (rest coordinates: where the tissue was cut) and its tip's
positions from DIR/timeseries.csv (where the tip was, the tissue deformed), seen from above
(x-y) and from the side (x-z), and the path's curvature against its length
(the `*_path_curvature` column). Writes DIR/tip_path.png and prints its path.

    scripts/plot_tip_path.py results/gel_bevel_steering
"""
import argparse
import csv
import json
import math
import os
import sys


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dir", help="output directory of `needle_sim run`")
    ap.add_argument("--out", help="image file (default DIR/tip_path.png)")
    a = ap.parse_args()
    try:  # the run's files first: a bad directory is reported without loading matplotlib
        with open(os.path.join(a.dir, "summary.json")) as f:
            summary = json.load(f)
        needles = {n: summary["needles"][n] for n in summary["names"]["needles"]}  # scene order
        with open(os.path.join(a.dir, "timeseries.csv")) as f:
            rows = list(csv.DictReader(f))
    except (OSError, ValueError, KeyError) as e:
        print("plot_tip_path: cannot read the run in %s: %s" % (a.dir, e), file=sys.stderr)
        return 2
    paths = {n: v["cut_path"] for n, v in needles.items() if v.get("cut_path")}
    if not paths:
        print("plot_tip_path: no needle in %s cut a path (no interaction, or no puncture)" % a.dir, file=sys.stderr)
        return 2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(3, 1, figsize=(8, 10))
    for name, path in paths.items():
        x = [1e3 * p[0] for p in path]
        for k, (axis, label) in enumerate([(1, "y"), (2, "z")]):
            ax[k].plot(x, [1e3 * p[axis] for p in path], "-", label="%s cut path (rest)" % name)
            tips = [r for r in rows if r.get(name + "_state") in ("inserted", "punctured")]
            ax[k].plot([1e3 * float(r[name + "_tip_x"]) for r in tips],
                       [1e3 * float(r["%s_tip_%s" % (name, label)]) for r in tips], ":",
                       label="%s tip (deformed tissue)" % name)
            ax[k].set_xlabel("x [mm]")
            ax[k].set_ylabel("%s [mm]" % label)
            ax[k].legend(fontsize=8)
            ax[k].grid(True, alpha=0.3)
        col = name + "_path_curvature"
        if rows and col in rows[0]:
            pts = [(1e3 * float(r[name + "_path_length"]), float(r[col])) for r in rows
                   if r[col] not in ("", "nan") and math.isfinite(float(r[col]))]
            ax[2].plot([p[0] for p in pts], [p[1] for p in pts], label=name)
    ax[0].set_title("cut path seen from above (x-y) and from the side (x-z)")
    ax[2].set_xlabel("cut path length [mm]")
    ax[2].set_ylabel("curvature of the last 5 mm [1/m]")
    ax[2].grid(True, alpha=0.3)
    ax[2].legend(fontsize=8)
    fig.tight_layout()
    out = a.out or os.path.join(a.dir, "tip_path.png")
    fig.savefig(out, dpi=90)
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())

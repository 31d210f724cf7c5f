"""Plots of one `needle_sim run` (the README's first run): what the paper's figures show for
the phantom insertion, from DIR/timeseries.csv:
  - probe displacement magnitude against time (every probe, µm); a scene without probes
    (the DBS scenes) shows its targets' displacement from rest instead (mm: the brain shift
    included),
  - the tissue's DOFs against time (the adaptive mesh following the needle),
  - the axial force of each needle on its holder against time (what a force sensor reads:
    the column <needle>_axial_force, negative when the tissue resists the insertion).
The names come from DIR/summary.json, in scene order. Writes DIR/run.png and prints its path.

    scripts/plot_run.py results/phantom_insertion_adaptive
"""
import argparse
import math
import os
import sys

import matplotlib

from ..run_outputs import axial_force_label, load_rows, load_summary, names

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def top_panel(summary):
    """The displacements the top panel shows: (columns' names, scale to the unit, axis label)."""
    probes = names(summary, "probes")
    if probes:
        return probes, 1e6, "probe |u| [µm]"
    targets = names(summary, "targets")
    return targets, 1e3, ("target |u| from rest [mm]" if targets else "no probes or targets")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dir", help="output directory of `needle_sim run`")
    ap.add_argument("--out", help="image file (default DIR/run.png)")
    a = ap.parse_args()
    path = os.path.join(a.dir, "timeseries.csv")
    if not os.path.exists(path):
        print("plot_run: no %s (did the run finish?)" % path, file=sys.stderr)
        return 2
    try:
        summary, rows = load_summary(a.dir), load_rows(a.dir)
        needles = names(summary, "needles")
    except (OSError, ValueError, KeyError) as e:
        print("plot_run: cannot read the run in %s: %s" % (a.dir, e), file=sys.stderr)
        return 2
    if not rows:
        print("plot_run: %s has no rows" % path, file=sys.stderr)
        return 2
    t = [float(r["t"]) for r in rows]
    fig, ax = plt.subplots(3, 1, figsize=(8, 9), sharex=True)
    shown, scale, what = top_panel(summary)
    for p in shown:
        u = [math.sqrt(sum(float(r[p + "_u" + d]) ** 2 for d in "xyz")) * scale for r in rows]
        ax[0].plot(t, u, label=p, lw=1)
    ax[0].set_ylabel(what)
    if shown:
        ax[0].legend(ncol=4, fontsize=7)
    dofs_col = "dofs"
    ax[1].plot(t, [int(r[dofs_col]) for r in rows], color="k", lw=1)
    ax[1].set_ylabel("DOFs (all bodies)")
    for n in needles:
        ax[2].plot(t, [1e3 * float(r[n + "_axial_force"]) for r in rows], label=n, lw=1)
    ax[2].set_ylabel(axial_force_label("mN"), fontsize=9)
    ax[2].set_xlabel("t [s]")
    if needles:
        ax[2].legend(fontsize=7)
    for x in ax:
        x.grid(alpha=0.3)
    fig.suptitle(os.path.basename(os.path.normpath(a.dir)))
    fig.tight_layout()
    out = a.out or os.path.join(a.dir, "run.png")
    fig.savefig(out, dpi=110)
    print("plots: %s" % out)
    return 0


if __name__ == "__main__":
    sys.exit(main())

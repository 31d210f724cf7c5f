"""Probe displacement against step for several runs of the phantom insertion, like the
paper's figures (Bui et al., Figs. "displacement along the needle" and "radial").

Sample run (after the three shipped insertion scenes have been run):

    for n in 8x4x4 16x8x8 32x16x16; do
      devel/lib/needle_sim/needle_sim run config/scenes/phantom_insertion_$n.yaml \
          --out results/phantom_insertion_$n
    done
    scripts/plot_probes.py results/phantom_insertion_8x4x4 \
        results/phantom_insertion_16x8x8 results/phantom_insertion_32x16x16 --out results/plots

It writes one PNG per probe (displacement magnitude, and its component along the needle axis,
against step, one curve per run, labelled with the run's scene and largest DOFs) and two overview PNGs for the
finest run: all probes along the path, all probes on the radial line.
"""
import argparse
import csv
import math
import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from ..run_outputs import load_summary, names


def load(run_dir):
    path = os.path.join(run_dir, "timeseries.csv")
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except OSError as e:
        sys.exit(f"plot_probes: cannot read {path}: {e.strerror}")
    if not rows:
        sys.exit(f"plot_probes: {path} has no rows")
    try:
        s = load_summary(run_dir)
        probes = names(s, "probes")
    except (OSError, ValueError, KeyError) as e:
        sys.exit(f"plot_probes: cannot read {run_dir}/summary.json: {e}")
    name = s.get("scene", {}).get("name", os.path.basename(os.path.normpath(run_dir)))
    # The run's largest total DOFs: an adaptive run ends on the mesh it coarsened back to
    # (the 8x4x4's 675 DOFs after the withdrawal), which names nothing.
    try:
        counts = [int(r["dofs"]) for r in rows]
        dofs = f"{max(counts):,}" if min(counts) == max(counts) else f"up to {max(counts):,}"
    except (KeyError, ValueError):
        dofs = str(s.get("tissue", {}).get("dofs", "?"))
    return {"name": name, "dofs": dofs, "rows": rows, "probes": sorted(probes)}


def series(run, probe, component):
    steps, values = [], []
    for r in run["rows"]:
        u = [float(r[f"{probe}_u{c}"]) for c in "xyz"]
        steps.append(int(r["step"]))
        values.append(1e3 * (math.sqrt(sum(x * x for x in u)) if component == "norm" else u[0]))
    return steps, values


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="output directories of needle_sim run")
    ap.add_argument("--out", default="results/plots", help="directory for the PNG files")
    ap.add_argument("--component", choices=["norm", "x"], default="norm",
                    help="displacement magnitude, or its x component (the phantom's needle axis)")
    args = ap.parse_args()
    runs = [load(d) for d in args.runs]
    os.makedirs(args.out, exist_ok=True)
    common = [p for p in runs[0]["probes"] if all(p in r["probes"] for r in runs)]
    if not common:
        sys.exit("plot_probes: the runs have no probe in common")
    written = []
    for probe in common:
        fig, ax = plt.subplots(figsize=(6, 4))
        for r in runs:
            s, v = series(r, probe, args.component)
            ax.plot(s, v, label=f"{r['name']} ({r['dofs']} DOFs)")
        ax.set_xlabel("step")
        ax.set_ylabel(("|u|" if args.component == "norm" else "u_x") + f" of probe {probe} [mm]")
        ax.set_title(f"Probe {probe}")
        ax.grid(True, alpha=0.3)
        ax.legend()
        fig.tight_layout()
        path = os.path.join(args.out, f"probe_{probe}.png")
        fig.savefig(path, dpi=120)
        plt.close(fig)
        written.append(path)
    finest = runs[-1]
    groups = {"along_path": [p for p in common if p[1:].isdigit()],
              "radial": [p for p in common if p == "p1" or (p.startswith("p1") and p[2:].isalpha())]}
    for group, probes in groups.items():
        if not probes:
            continue
        fig, ax = plt.subplots(figsize=(6, 4))
        for p in probes:
            s, v = series(finest, p, args.component)
            ax.plot(s, v, label=p)
        ax.set_xlabel("step")
        ax.set_ylabel("|u| [mm]" if args.component == "norm" else "u_x [mm]")
        ax.set_title(f"{finest['name']} ({finest['dofs']} DOFs): probes {group.replace('_', ' ')}")
        ax.grid(True, alpha=0.3)
        ax.legend(ncol=2, fontsize="small")
        fig.tight_layout()
        path = os.path.join(args.out, f"probes_{group}.png")
        fig.savefig(path, dpi=120)
        plt.close(fig)
        written.append(path)
    for p in written:
        print(p)


if __name__ == "__main__":
    main()

"""Run time against probe error on the paper's phantom insertion: uniform 8x4x4, 16x8x8 and
32x16x16 meshes against adaptive meshes from 8x4x4 (Bui et al., Section 3.1). The error of a
run is the largest difference of any probe displacement (probes 1..7 on the path, 1A..1E
on the radial line) at any step from the 32x16x16 run, relative to the largest probe
displacement of that run; also its time mean, and separately the puncture instant (a
one-step transient that an adaptive mesh resolves one step late).

Sample run (about 4 minutes on the 2-core machine, most of it the 32x16x16 reference):

    scripts/adaptivity_study.py --out results/adaptivity_study

writes results/adaptivity_study/{study.csv, study.md, runtime_vs_error.png} and one run
directory per configuration (kept: --reuse skips runs whose summary.json says ok); with
--write-doc the table goes into doc/benchmarks.md's block and the figure into doc/.
"""
import math
import os
import shutil

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from ..run_outputs import names
from .. import paths
from .runs import SCENES, parse_args, run_all, write_csv, write_doc_block


# name, scene file, overrides
RUNS = [
    ("uniform 8x4x4", "phantom_insertion_8x4x4.yaml", []),
    ("uniform 16x8x8", "phantom_insertion_16x8x8.yaml", []),
    ("uniform 32x16x16", "phantom_insertion_32x16x16.yaml", []),
    # Without refinement ahead of the tip: the mesh follows the estimate alone.
    ("adaptive theta 0.3, 1 level", "phantom_insertion_adaptive.yaml", ["adaptivity.max_level=1", "adaptivity.lookahead=0"]),
    ("adaptive theta 0.3, 2 levels", "phantom_insertion_adaptive.yaml", ["adaptivity.lookahead=0"]),
    ("adaptive theta 0.1, 2 levels", "phantom_insertion_adaptive.yaml",
     ["adaptivity.theta=0.1", "adaptivity.coarsen.theta_coarsen=0.02", "adaptivity.lookahead=0"]),
    ("adaptive theta 0.3, 2 levels, no coarsening", "phantom_insertion_adaptive.yaml",
     ["adaptivity.coarsen.enabled=false", "adaptivity.lookahead=0"]),
    # Refinement ahead of the tip (adaptivity.lookahead: the trajectory's next 0.2 or 0.4 s);
    # the shipped scene refines 0.4 s ahead.
    ("adaptive theta 0.3, 2 levels, lookahead 0.2 s", "phantom_insertion_adaptive.yaml", ["adaptivity.lookahead=0.2"]),
    ("adaptive theta 0.3, 2 levels, lookahead 0.4 s (shipped)", "phantom_insertion_adaptive.yaml", []),
    ("adaptive theta 0.1, 2 levels, lookahead 0.4 s", "phantom_insertion_adaptive.yaml",
     ["adaptivity.theta=0.1", "adaptivity.coarsen.theta_coarsen=0.02"]),
]
REFERENCE = "uniform 32x16x16"


def probe_series(summary, rows):
    """Each probe's displacement per step (the probes named in summary.json)."""
    return {n: [(float(r[n + "_ux"]), float(r[n + "_uy"]), float(r[n + "_uz"])) for r in rows]
            for n in names(summary, "probes")}


def main():
    args = parse_args(__doc__, "adaptivity_study",
                      lambda ap: ap.add_argument("--write-doc", action="store_true",
                                                 help="write the table into doc/benchmarks.md and the figure into doc/"))

    results = {}
    for name, (summary, _, rows) in run_all(args.tool, SCENES, args.out, [(n, sc, [a for x in sets for a in ("--set", x)])
                                                                           for n, sc, sets in RUNS], args.reuse).items():
        results[name] = (summary, rows, probe_series(summary, rows))

    _, ref_rows, ref = results[REFERENCE]
    umax = max(math.sqrt(sum(c * c for c in u)) for s in ref.values() for u in s)
    # The puncture is a one-step transient: reported separately (steps within 10 of the
    # first contact), since an adaptive mesh follows such an event one step later.
    contact = next(i for i, r in enumerate(ref_rows) if r.get("needle_state", "approaching") != "approaching")
    table = []
    for name, _, _ in RUNS:
        summary, rows, series = results[name]
        per_step = [max(math.dist(s[k], ref[p][k]) for p, s in series.items()) / umax for k in range(len(ref_rows))]
        steady = [e for k, e in enumerate(per_step) if abs(k - contact) > 10]
        ad = summary.get("adaptivity", {})
        dofs = [int(r["dofs"]) for r in rows]
        table.append({
            "run": name,
            "tissue_dofs_max": ad.get("tissue_dofs_max", summary["tissue"]["dofs"]),
            "dofs_median": sorted(dofs)[len(dofs) // 2],
            "wall_s": summary["wall_time_s"],
            "step_median_ms": summary["step_ms"]["median"],
            "step_max_ms": summary["step_ms"]["max"],
            "adapt_share": ad.get("adapt_share_of_run", 0.0),
            "error_max": max(steady),
            "error_mean": sum(per_step) / len(per_step),
            "error_at_puncture": max(per_step),
        })
    ref_wall = next(t["wall_s"] for t in table if t["run"] == REFERENCE)
    for t in table:
        t["speedup_vs_32"] = ref_wall / t["wall_s"]

    write_csv(os.path.join(args.out, "study.csv"), table)
    with open(os.path.join(args.out, "study.md"), "w") as f:
        f.write("| run | tissue DOFs max | wall s | speed-up vs 32x16x16 | step median ms | step max ms | "
                "adaptivity share | probe error max | probe error time-mean | probe error at puncture |\n")
        f.write("|---|---|---|---|---|---|---|---|---|---|\n")
        for t in table:
            f.write(f"| {t['run']} | {t['tissue_dofs_max']:,} | {t['wall_s']:.2f} | "
                    f"{t['speedup_vs_32']:.1f}x | {t['step_median_ms']:.3f} | {t['step_max_ms']:.1f} | "
                    f"{100 * t['adapt_share']:.1f} % | {t['error_max']:.3f} | {t['error_mean']:.4f} | "
                    f"{t['error_at_puncture']:.3f} |\n")
    print(open(os.path.join(args.out, "study.md")).read())

    fig, ax = plt.subplots(figsize=(7, 5))
    for t in table:
        if t["run"] == REFERENCE:
            continue
        err = t["error_max"]
        marker = "s" if t["run"].startswith("uniform") else "o"
        ax.loglog(t["wall_s"], err, marker, markersize=8, label=f"{t['run']} ({t['tissue_dofs_max']:,} DOFs)")
    ax.axvline(ref_wall, color="gray", linestyle="--", label=f"{REFERENCE} run time ({ref_wall:.0f} s)")
    ax.set_xlabel("run time [s] (5,000 steps)")
    ax.set_ylabel("max probe error vs 32x16x16 (relative, outside the puncture step)")
    ax.set_title("Phantom insertion: run time against probe error")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    png = os.path.join(args.out, "runtime_vs_error.png")
    fig.savefig(png, dpi=120)
    print("wrote", png)
    if args.write_doc:
        with open(os.path.join(args.out, "study.md")) as f:
            write_doc_block("benchmarks.md", "adaptivity_study", f.read(),
                            "scripts/adaptivity_study.py --out results/adaptivity_study --write-doc")
        shutil.copyfile(png, os.path.join(paths.share_dir(), "doc", "adaptivity_runtime_vs_error.png"))


if __name__ == "__main__":
    main()

"""How far the DBS prediction moves when only the linear solver does (doc/benchmarks.md
"Reproducibility"): the same scene with the conjugate-gradient tolerance (the scene's 1e-8,
1e-10, 1e-12) and the background factor's swap lag (the scene's 4 steps, 2, 6; the node takes a
refresh as soon as it is ready, an effective lag that varies from run to run) changed, and the
node's lagged rotations (solver.linear.rotation_drift 0.01 rad, what ~rotation_drift takes for
the brain); nothing else. Every run is a correct solution to within its tolerance; what differs between them is
the solver's round-off-sized path. Where the prediction goes through a stick-slip event of the
shaft's grip (a release whose timing a tiny perturbation moves), the runs part, and their
spread is a limit on what the prediction can be trusted to, below which neither a finer mesh
nor a sharper error bound helps.

    scripts/reproducibility_study.py --out results/reproducibility --jobs 2              # 24 runs, about 4 min
    scripts/reproducibility_study.py --out results/reproducibility --jobs 2 --write-doc  # + its block in the docs

writes DIR/runs.csv, DIR/runs.md and DIR/spread.md (per scene: each quantity's range over the
runs and the shipped settings' value).
"""
import argparse
import concurrent.futures
import os
import sys

from .. import paths
from . import runs
from .dbs import CANNULA, fmt, run, series

# label, scene, extra arguments (the shipped flagship: the adaptive mesh on the re-planned
# trajectory; the coarse mesh on the planned one, its worst case for the shaft's grip)
SCENES = [("dbs_adaptive, replanned", "dbs_adaptive.yaml", ["--set", "brain_shift.replan=true"]),
          ("dbs_coarse, planned", "dbs_coarse.yaml", [])]
TOLERANCES = [1e-8, 1e-10, 1e-12]
LAGS = [4, 2, 6]
# (tolerance, lag, rotation drift): the grid with the rotations of every step, then the node's
# lagged rotations at the three lags.
RUNS = [(t, g, 0.0) for t in TOLERANCES for g in LAGS] + [(1e-8, g, 0.01) for g in LAGS]
SHIPPED = (1e-8, 4, 0.0)
QUANTITIES = [("final_distance_mm", "final electrode–STN distance [mm]"),
              ("stn_motion_max_mm", "largest STN motion since the shift [mm]"),
              ("stn_motion_final_mm", "STN motion at the end [mm]"),
              ("cannula_push_N", "cannula's peak push [N]"),
              ("cannula_pull_N", "cannula's peak pull [N]")]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=paths.results_dir("reproducibility"))
    ap.add_argument("--tool", default=paths.tool())
    ap.add_argument("--reuse", action="store_true", help="keep runs whose summary.json says ok")
    ap.add_argument("--jobs", type=int, default=1, help="runs at a time (each uses one core)")
    ap.add_argument("--write-doc", action="store_true", help="write the tables into doc/benchmarks.md")
    a = ap.parse_args()
    if not os.access(a.tool, os.X_OK):
        sys.exit(f"reproducibility_study: no needle_sim tool at {a.tool} (build first: bash scripts/test.sh)")
    os.makedirs(a.out, exist_ok=True)
    jobs = {}
    for label, scene, extra in SCENES:
        for tol, lag, drift in RUNS:
            d = os.path.join(a.out, runs.slug(f"{scene[:-5]} tol{tol:g} lag{lag}" + (f" drift{drift:g}" if drift else "")))
            jobs[(label, tol, lag, drift)] = (d, scene, extra + ["--set", f"solver.linear.tolerance={tol:g}",
                                                                 "--set", f"solver.linear.async_lag={lag}",
                                                                 "--set", f"solver.linear.rotation_drift={drift:g}"])
    with concurrent.futures.ThreadPoolExecutor(max_workers=a.jobs) as ex:
        futures = {k: ex.submit(run, a.tool, d, scene, extra, a.reuse) for k, (d, scene, extra) in jobs.items()}
        results = {k: f.result() for k, f in futures.items()}

    table = []
    for (label, tol, lag, drift), (summary, rows) in results.items():
        row = {"scene": label, "cg_tolerance": f"{tol:g}", "async_lag": lag, "rotation_drift": f"{drift:g}",
               "status": summary.get("status")}
        if rows:
            s = series(rows)
            row.update({"final_distance_mm": s["distance"][-1], "stn_motion_max_mm": max(s["motion"]),
                        "stn_motion_final_mm": s["motion"][-1], "cannula_push_N": min(s[CANNULA]),
                        "cannula_pull_N": max(s[CANNULA])})
        table.append(row)
    runs.write_csv(os.path.join(a.out, "runs.csv"), table)
    keys = ["scene", "cg_tolerance", "async_lag", "rotation_drift", "status"] + [k for k, _ in QUANTITIES]
    md = "| " + " | ".join(keys) + " |\n|" + "---|" * len(keys) + "\n"
    for r in table:
        md += "| " + " | ".join(fmt(r.get(k, "")) for k in keys) + " |\n"
    spread = "| scene | quantity | shipped (1e-8, lag 4, no drift) | range over the runs | spread |\n|---|---|---|---|---|\n"
    for label, _, _ in SCENES:
        ok = [r for r in table if r["scene"] == label and "final_distance_mm" in r]
        shipped = [r for r in ok if (float(r["cg_tolerance"]), r["async_lag"], float(r["rotation_drift"])) == SHIPPED]
        for key, name in QUANTITIES:
            v = [r[key] for r in ok]
            if not v:
                continue
            spread += "| %s | %s | %s | %s to %s | %s |\n" % (
                label, name, fmt(shipped[0][key]) if shipped else "—", fmt(min(v)), fmt(max(v)), fmt(max(v) - min(v)))
    spread += "\n(%d of %d runs ok.)\n" % (sum(1 for r in table if "final_distance_mm" in r), len(table))
    for name, text in (("runs.md", md), ("spread.md", spread)):
        with open(os.path.join(a.out, name), "w") as f:
            f.write(text)
    print(spread)
    print(md)
    if a.write_doc:
        command = "scripts/reproducibility_study.py " + " ".join(x for x in sys.argv[1:] if x != "--reuse")
        runs.write_doc_block("benchmarks.md", "dbs_reproducibility", spread + "\n" + md, command)
    return 0


if __name__ == "__main__":
    sys.exit(main())

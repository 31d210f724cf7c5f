"""The paper's deep-brain-stimulation study (Bui et al., Section 3.2), with insertion
mechanics that matter (doc/benchmarks.md "DBS"): brain shift, cannula with electrode to the
left STN, cannula withdrawn, the shaft friction from measured values (dbs_coarse.yaml's
`interaction` section). Two trajectories:
  - planned: aimed at the STN before the shift (the scene as it is); the final
    electrode-STN distance is the shift plus what the insertion does;
  - replanned: re-aimed at the shifted STN through the same entry point
    (`brain_shift.replan`, the intraoperative case); the final distance comes from the
    insertion and the retraction alone (the paper reports about 2.9 mm).
For both, the meshes: uniform coarse (16 mm), uniform fine (8 mm), adaptive (SPR, theta 0.6)
and goal-oriented adaptive (on the STN), and with --reference a uniform 4 mm mesh, finer
than fine, as the reference. Per run: the STN's motion since the shift, the electrode
tip-STN distance, the cannula's axial force on its holder (a force sensor's reading: negative
when the tissue resists), DOFs
and times; the goal-oriented bound on the STN's displacement error (coarse, adaptive and goal
runs) against its true error (the difference to the reference, or to fine without it).

    scripts/dbs_study.py --out results/dbs_study                       # 8 runs, about 15 min
    scripts/dbs_study.py --out results/dbs_study --reference --reuse   # + the 4 mm runs, about 2 h
    scripts/dbs_study.py --out results/dbs_study --sensitivity --reuse # + 20 adaptive runs, about 10 min

writes DIR/{study.csv, study.md, stn_motion_<trajectory>.png, distance_<trajectory>.png,
holder_force_<trajectory>.png, stn_bound_<trajectory>.png} and one run directory per
configuration; --sensitivity adds DIR/sensitivity.{csv,md,png}: the final electrode-STN
distance and the STN's largest motion on the re-planned trajectory (adaptive mesh) against
the grip pressure and the friction coefficient. --reuse keeps runs whose summary.json says ok.
--write-doc writes study.md and sensitivity.md into doc/benchmarks.md's blocks and copies the
figures it shows into doc/.
"""
import argparse
import concurrent.futures
import csv
import json
import math
import os
import shutil
import subprocess
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from .. import paths
from ..run_outputs import axial_force_label
from . import runs
from .runs import SCENES, slug, write_csv

TARGET, ELECTRODE, CANNULA = "STN_L", "electrode", "cannula"
ESTIMATE = ["--target-error", "--target-error-every", "10"]
# label, scene, extra arguments, has a bound
MESHES = [
    ("coarse (16 mm)", "dbs_coarse.yaml", ESTIMATE, True),
    ("fine (8 mm)", "dbs_fine.yaml", [], False),
    ("adaptive (SPR)", "dbs_adaptive.yaml", ESTIMATE, True),
    ("goal-adaptive (STN)", "dbs_goal.yaml", [], True),  # the goal estimator computes the bound anyway
]
REFERENCE = ("reference (4 mm)", "dbs_fine.yaml", ["--set", "tissue.grid.refine=2"], False)
TRAJECTORIES = [("planned", []), ("replanned", ["--set", "brain_shift.replan=true"])]
GRIPS = [0.0, 200.0, 400.0, 800.0, 1600.0]
FRICTIONS = [0.05, 0.15, 0.255, 0.35]


def run(tool, out, scene, extra, reuse):
    d = out
    summary = os.path.join(d, "summary.json")
    if not (reuse and os.path.exists(summary) and json.load(open(summary)).get("status") == "ok"):
        cmd = [tool, "run", os.path.join(SCENES, scene), "--out", d, "--quiet"] + extra
        print("+", " ".join(cmd), flush=True)
        r = subprocess.run(cmd, check=False, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        if not os.path.exists(summary):  # refused before any step (exit 2): say why, go on
            print(r.stderr.strip(), file=sys.stderr)
            return {"status": "failed", "message": r.stderr.strip()}, []
    s = json.load(open(summary))
    rows = list(csv.DictReader(open(os.path.join(d, "timeseries.csv")))) if s.get("status") == "ok" else []
    return s, rows


def run_many(tool, jobs, reuse):
    """jobs: {key: (dir, scene, extra)} -> {key: (summary, rows)}, `--jobs` at a time."""
    with concurrent.futures.ThreadPoolExecutor(max_workers=ARGS.jobs) as ex:
        futures = {k: ex.submit(run, tool, d, scene, extra, reuse) for k, (d, scene, extra) in jobs.items()}
        return {k: f.result() for k, f in futures.items()}


def vec(r, prefix):
    return [float(r[prefix + c]) for c in "xyz"]


def series(rows):
    """Per step: STN motion since step 0 [mm], electrode tip-STN distance [mm], the cannula's
    and the electrode's axial force on the holder [N] (the columns <needle>_axial_force, what
    a force sensor reads: negative when the tissue resists), the STN bound [mm] (NaN without
    one), the STN position [m]."""
    x0 = vec(rows[0], f"{TARGET}_")
    out = {"step": [], "motion": [], "distance": [], "cannula": [], "electrode": [], "bound": [], "position": []}
    for r in rows:
        x = vec(r, f"{TARGET}_")
        out["step"].append(int(r["step"]))
        out["position"].append(x)
        out["motion"].append(1000 * math.dist(x, x0))
        out["distance"].append(1000 * float(r[f"{TARGET}_dist_{ELECTRODE}"]))
        for n in (CANNULA, ELECTRODE):
            out[n].append(float(r[f"{n}_axial_force"]))
        b = r.get(f"{TARGET}_err_bound", "nan")
        out["bound"].append(1000 * float(b) if b not in ("", "nan") else float("nan"))
    return out


def main():
    global ARGS
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=paths.results_dir("dbs_study"))
    ap.add_argument("--tool", default=paths.tool())
    ap.add_argument("--reuse", action="store_true", help="keep runs whose summary.json says ok")
    ap.add_argument("--reference", action="store_true", help="also the uniform 4 mm mesh, the reference (about 2 h)")
    ap.add_argument("--sensitivity", action="store_true", help="the final distance against grip pressure and friction")
    ap.add_argument("--jobs", type=int, default=1, help="runs at a time (each uses one core)")
    ap.add_argument("--write-doc", action="store_true",
                    help="write the tables into doc/benchmarks.md and the figures it shows into doc/")
    ARGS = args = ap.parse_args()
    if not os.access(args.tool, os.X_OK):
        sys.exit(f"dbs_study: no needle_sim tool at {args.tool} (build first: bash scripts/test.sh)")
    os.makedirs(args.out, exist_ok=True)

    meshes = MESHES + ([REFERENCE] if args.reference else [])
    jobs = {(traj, label): (os.path.join(args.out, slug(f"{traj} {label}")), scene, extra + textra)
            for traj, textra in TRAJECTORIES for label, scene, extra, _ in meshes}
    results = run_many(args.tool, jobs, args.reuse)

    table = []
    for traj, _ in TRAJECTORIES:
        ref_label = REFERENCE[0] if args.reference else MESHES[1][0]
        ref_summary, ref_rows = results[(traj, ref_label)]
        ref = series(ref_rows) if ref_rows else None
        for label, _, _, has_bound in meshes:
            summary, rows = results[(traj, label)]
            row = {"trajectory": traj, "mesh": label, "status": summary.get("status")}
            if not rows:
                table.append(row)
                continue
            s = series(rows)
            ad = summary.get("adaptivity", {})
            tgt = summary["targets"][TARGET]
            row.update({
                "tissue_dofs_max": ad.get("tissue_dofs_max", summary["tissue"]["dofs"]),
                "wall_s": round(summary["wall_time_s"], 1),
                "step_median_ms": round(summary["step_ms"]["median"], 2),
                "stn_motion_max_mm": max(s["motion"]),
                "stn_motion_final_mm": s["motion"][-1],
                "final_distance_mm": s["distance"][-1],
                "cannula_axial_force_min_N": min(s[CANNULA]),  # the insertion the tissue resisted most
                "cannula_axial_force_max_N": max(s[CANNULA]),
                "unconverged_steps": summary.get("interaction", {}).get("unconverged_steps"),
            })
            if ref is not None:
                n = min(len(s["position"]), len(ref["position"]))
                err = [1000 * math.dist(s["position"][k], ref["position"][k]) for k in range(n)]
                row["stn_true_error_max_mm"] = max(err)
                row["stn_true_error_final_mm"] = err[-1]
                row["final_distance_vs_ref_mm"] = s["distance"][-1] - ref["distance"][-1]
                row["cannula_axial_force_min_vs_ref"] = (min(s[CANNULA]) / min(ref[CANNULA]) if min(ref[CANNULA]) < 0
                                                         else float("nan"))
                if has_bound:
                    b = s["bound"][:n]
                    valid = [k for k in range(n) if not math.isnan(b[k])]
                    row["stn_bound_final_mm"] = b[-1]
                    row["stn_bound_max_mm"] = max(b[k] for k in valid) if valid else float("nan")
                    row["bound_covers_pct"] = (100.0 * sum(1 for k in valid if b[k] >= err[k]) / len(valid)) if valid else float("nan")
                    row["bound_over_error_final"] = b[-1] / err[-1] if err[-1] > 0 else float("nan")
            table.append(row)
    keys = []
    for r in table:
        keys += [k for k in r if k not in keys]
    table = [{k: r.get(k, "") for k in keys} for r in table]
    write_csv(os.path.join(args.out, "study.csv"), table)
    write_markdown(os.path.join(args.out, "study.md"), table, keys, "reference (4 mm)" if args.reference else "fine (8 mm)")
    print(open(os.path.join(args.out, "study.md")).read())
    plots(args.out, results, meshes, args.reference)
    if args.sensitivity:
        sensitivity(args)
    if args.write_doc:
        write_doc(args)


# The figures doc/benchmarks.md shows, from the study's folder.
DOC_FIGURES = {"holder_force_replanned.png": "dbs_holder_force.png", "stn_motion_planned.png": "dbs_stn_motion_planned.png",
               "distance_replanned.png": "dbs_distance_replanned.png", "stn_bound_replanned.png": "dbs_stn_bound.png",
               "sensitivity.png": "dbs_sensitivity.png"}


def write_doc(args):
    """study.md (and sensitivity.md) into doc/benchmarks.md's blocks, the figures into doc/."""
    command = "scripts/dbs_study.py " + " ".join(a for a in sys.argv[1:] if a not in ("--reuse",))
    with open(os.path.join(args.out, "study.md")) as f:
        runs.write_doc_block("benchmarks.md", "dbs_study", f.read(), command)
    if args.sensitivity:
        with open(os.path.join(args.out, "sensitivity.md")) as f:
            runs.write_doc_block("benchmarks.md", "dbs_sensitivity", f.read(), command)
    for src, dst in DOC_FIGURES.items():
        if os.path.exists(os.path.join(args.out, src)):
            shutil.copyfile(os.path.join(args.out, src), os.path.join(paths.share_dir(), "doc", dst))


def fmt(v):
    if isinstance(v, float):
        return "—" if math.isnan(v) else (f"{v:.3g}" if abs(v) < 100 else f"{v:,.0f}")
    return f"{v:,}" if isinstance(v, int) else str(v)


def write_markdown(path, table, keys, ref_name):
    with open(path, "w") as f:
        f.write(f"True errors against the {ref_name} run of the same trajectory.\n\n")
        f.write("| " + " | ".join(keys) + " |\n|" + "---|" * len(keys) + "\n")
        for r in table:
            f.write("| " + " | ".join(fmt(r[k]) for k in keys) + " |\n")


def plots(out, results, meshes, reference):
    ref_label = REFERENCE[0] if reference else MESHES[1][0]
    for traj, _ in TRAJECTORIES:
        data = {label: series(results[(traj, label)][1]) for label, *_ in meshes if results[(traj, label)][1]}
        xlabel = "step (dt = 10 ms): insertion to step 872, cannula withdrawn from step 922"
        for name, key, ylabel, title in [
            ("stn_motion", "motion", "STN motion since the shift [mm]", "left STN: motion during insertion and withdrawal"),
            ("distance", "distance", "electrode tip - STN distance [mm]", "electrode tip to the left STN"),
            ("holder_force", CANNULA, "cannula: " + axial_force_label("N"), "what the cannula's force sensor reads"),
        ]:
            fig, ax = plt.subplots(figsize=(7.5, 4.5))
            for label, s in data.items():
                style = {"color": "k", "lw": 2, "alpha": 0.5} if label == ref_label else {"lw": 1}
                ax.plot(s["step"], s[key], label=label, **style)
            ax.set_xlabel(xlabel)
            ax.set_ylabel(ylabel)
            ax.set_title(f"{title} ({traj} trajectory)")
            if key == "distance":
                ax.set_ylim(0, 20)
            ax.grid(True, alpha=0.3)
            ax.legend(fontsize=8)
            fig.tight_layout()
            fig.savefig(os.path.join(out, f"{name}_{traj}.png"), dpi=120)
            plt.close(fig)
        # The bound against the true error (the distance to the reference's STN position).
        if ref_label not in data:
            continue
        ref = data[ref_label]
        fig, ax = plt.subplots(figsize=(7.5, 4.5))
        for (label, _, _, has_bound), color in zip(meshes, ["C0", "C1", "C2", "C3", "C4"]):
            if not has_bound or label not in data:
                continue
            s = data[label]
            n = min(len(s["step"]), len(ref["step"]))
            err = [1000 * math.dist(s["position"][k], ref["position"][k]) for k in range(n)]
            ax.semilogy(s["step"][:n], err, color=color, lw=1, label=f"{label}: true error")
            ax.semilogy(s["step"][:n], s["bound"][:n], color=color, lw=1, ls="--", label=f"{label}: bound")
        ax.set_xlabel("step")
        ax.set_ylabel("STN displacement error [mm]")
        ax.set_title(f"left STN: goal-oriented bound and true error against {ref_label} ({traj})")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(os.path.join(out, f"stn_bound_{traj}.png"), dpi=120)
        plt.close(fig)
        print("wrote plots for", traj)


def sensitivity(args):
    jobs = {}
    for g in GRIPS:
        for mu in FRICTIONS:
            d = os.path.join(args.out, "sensitivity", f"grip{g:g}_friction{mu:g}")
            jobs[(g, mu)] = (d, "dbs_adaptive.yaml", ["--set", "brain_shift.replan=true", "--set", f"interaction.grip_pressure={g}",
                                                       "--set", f"interaction.friction={mu}"])
    results = run_many(args.tool, jobs, args.reuse)
    table = []
    for (g, mu), (summary, rows) in results.items():
        row = {"grip_pressure_Pa": g, "friction": mu, "status": summary.get("status")}
        if rows:
            s = series(rows)
            row.update({"final_distance_mm": s["distance"][-1], "stn_motion_max_mm": max(s["motion"]),
                        "cannula_axial_force_min_N": min(s[CANNULA])})
        table.append(row)
    write_csv(os.path.join(args.out, "sensitivity.csv"), table)
    keys = list(table[0].keys())
    with open(os.path.join(args.out, "sensitivity.md"), "w") as f:
        f.write("| " + " | ".join(keys) + " |\n|" + "---|" * len(keys) + "\n")
        for r in table:
            f.write("| " + " | ".join(fmt(r.get(k, "")) for k in keys) + " |\n")
    print(open(os.path.join(args.out, "sensitivity.md")).read())
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for mu in FRICTIONS:
        rs = [r for r in table if r["friction"] == mu and "final_distance_mm" in r]
        axes[0].plot([r["grip_pressure_Pa"] for r in rs], [r["final_distance_mm"] for r in rs], "o-", label=f"friction {mu:g}")
        axes[1].plot([r["grip_pressure_Pa"] for r in rs], [r["stn_motion_max_mm"] for r in rs], "o-", label=f"friction {mu:g}")
    axes[0].set_ylabel("final electrode tip - STN distance [mm]")
    axes[1].set_ylabel("largest STN motion during the insertion [mm]")
    for ax in axes:
        ax.set_xlabel("grip pressure [Pa]")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
        ax.axvline(800, color="gray", ls=":", lw=1)
    fig.suptitle("re-planned trajectory, adaptive mesh: sensitivity to the shaft friction (scene: 800 Pa, 0.255)")
    fig.tight_layout()
    fig.savefig(os.path.join(args.out, "sensitivity.png"), dpi=120)
    print("wrote", os.path.join(args.out, "sensitivity.png"))


if __name__ == "__main__":
    main()

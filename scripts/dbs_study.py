#!/usr/bin/python3
"""The paper's deep-brain-stimulation result (Bui et al., Section 3.2): brain shift, cannula
with electrode to the left STN, cannula withdrawn; where does the electrode tip end up
relative to the STN? Runs the uniform coarse (16 mm), uniform fine (8 mm, one uniform
refinement) and adaptive (from 16 mm, theta 0.6, one level) scenes and compares them:
electrode tip-target distance and target displacement against step, maximum DOFs, brain
shift and step times, and the final electrode-target distance (adaptive against fine: the
goal is agreement within 0.2 mm).

Sample run (about 5 minutes on the 2-core machine, most of it the uniform fine run):

    scripts/dbs_study.py --out results/dbs_study

writes results/dbs_study/{study.csv, study.md, distance_vs_step.png,
target_displacement_vs_step.png} and one run directory per scene (with --vtu for the
adaptive run: tissue.vtu, surface.vtp for ParaView); --reuse keeps runs whose summary.json
says ok.
"""
import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from study_runs import SCENES, parse_args, run_all, write_csv  # noqa: E402


# name, scene file, extra arguments
RUNS = [
    ("uniform coarse (16 mm)", "dbs_coarse.yaml", []),
    ("uniform fine (8 mm)", "dbs_fine.yaml", []),
    ("adaptive (16 mm, theta 0.6, 1 level)", "dbs_adaptive.yaml", ["--vtu"]),
]
FINE, ADAPTIVE = RUNS[1][0], RUNS[2][0]
TARGET, ELECTRODE = "STN_L", "electrode"


def main():
    args = parse_args(__doc__, "dbs_study")

    results = {name: (summary, rows) for name, (summary, _, rows) in
               run_all(args.tool, SCENES, args.out, RUNS, args.reuse).items()}

    table = []
    for name, _, _ in RUNS:
        summary, rows = results[name]
        bs = summary["brain_shift"]
        tgt = summary["targets"][TARGET]
        ad = summary.get("adaptivity", {})
        table.append({
            "run": name,
            "tissue_dofs_max": ad.get("tissue_dofs_max", summary["tissue"]["dofs"]),
            "shift_dofs": bs["dofs"],
            "shift_passes": bs["passes"],
            "shift_s": bs["ms"] / 1000,
            "shift_load_scale": bs["load_scale"],
            "stn_shift_mm": 1000 * bs["target_shift"],
            "step_median_ms": summary["step_ms"]["median"],
            "step_max_ms": summary["step_ms"]["max"],
            "wall_s": summary["wall_time_s"],
            "final_distance_mm": 1000 * tgt["tip_distance"][ELECTRODE],
            "closest_mm": 1000 * tgt["tip_distance_min"][ELECTRODE],
            "stn_motion_during_insertion_mm": 1000 * tgt["motion_since_start"],
        })
    fine = next(t for t in table if t["run"] == FINE)
    for t in table:
        t["vs_fine_mm"] = t["final_distance_mm"] - fine["final_distance_mm"]
        t["speedup_vs_fine"] = fine["wall_s"] / t["wall_s"]

    write_csv(os.path.join(args.out, "study.csv"), table)
    with open(os.path.join(args.out, "study.md"), "w") as f:
        f.write("| run | tissue DOFs max | brain shift: DOFs, passes, s, load scale | STN shift mm | "
                "step median ms | wall s | speed-up vs fine | final electrode-STN mm | vs fine mm | "
                "STN motion during insertion mm |\n")
        f.write("|---|---|---|---|---|---|---|---|---|---|\n")
        for t in table:
            f.write(f"| {t['run']} | {t['tissue_dofs_max']:,} | {t['shift_dofs']:,}, {t['shift_passes']}, "
                    f"{t['shift_s']:.2f}, {t['shift_load_scale']:.2f} | {t['stn_shift_mm']:.2f} | "
                    f"{t['step_median_ms']:.2f} | {t['wall_s']:.1f} | {t['speedup_vs_fine']:.1f}x | "
                    f"{t['final_distance_mm']:.3f} | {t['vs_fine_mm']:+.3f} | "
                    f"{t['stn_motion_during_insertion_mm']:.3f} |\n")
    print(open(os.path.join(args.out, "study.md")).read())

    # Like the paper's figures: uniform fine against adaptive (coarse for reference).
    plots = [
        ("distance_vs_step.png", lambda r: 1000 * float(r[f"{TARGET}_dist_{ELECTRODE}"]),
         "electrode tip - STN distance [mm]", "Electrode tip to target (left STN)"),
        ("target_displacement_vs_step.png", lambda r: 1000 * float(r[f"{TARGET}_u"]),
         "STN displacement from planning [mm]", "Target (left STN) displacement, brain shift included"),
    ]
    for png, value, ylabel, title in plots:
        fig, ax = plt.subplots(figsize=(7, 4.5))
        for name, _, _ in RUNS:
            summary, rows = results[name]
            t = next(x for x in table if x["run"] == name)
            style = {"linestyle": ":", "color": "gray"} if "coarse" in name else {}
            ax.plot([int(r["step"]) for r in rows], [value(r) for r in rows], label=f"{name}, max {t['tissue_dofs_max']:,} DOFs",
                    **style)
        ax.set_xlabel("step (dt = 10 ms): insertion to step 872, cannula withdrawn from step 922")
        ax.set_ylabel(ylabel)
        ax.set_title(title)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
        if png.startswith("target"):
            ax.set_ylim(bottom=0)
        fig.tight_layout()
        fig.savefig(os.path.join(args.out, png), dpi=120)
        print("wrote", os.path.join(args.out, png))

    ad = next(t for t in table if t["run"] == ADAPTIVE)
    print(f"final electrode-STN distance: adaptive {ad['final_distance_mm']:.3f} mm, fine "
          f"{fine['final_distance_mm']:.3f} mm, difference {abs(ad['vs_fine_mm']):.3f} mm (goal <= 0.2 mm)")


if __name__ == "__main__":
    main()

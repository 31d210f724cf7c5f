"""Verification of the goal-oriented estimate of target-displacement errors (issue #17,
doc/verification.md "Error on target motion"). For each static box scene of
test/data/target_error/ and each target (interior, edge, face):
  - uniform meshes 8x4x4, 16x8x8, 32x16x16 (and 64x32x32 for the reference), and an adaptive
    run (goal-oriented on that target, from 8x4x4);
  - the reference: Richardson extrapolation of the regularised displacement Q (the mean over
    a ball of radius 1.25 mm, one element of the 32x16x16 grid) from the three finest uniform
    meshes, with the rate fitted per component; its error bar: the difference from the
    extrapolation of the three coarser ones;
  - per mesh and component with a non-negligible error (above 1 % of the largest): the true
    error Q_ref - Q_h, the estimate, the effectivity (estimate / true error), and whether the
    bound covers the true error's norm.
Writes DIR/target_error_study.md (tables and a summary: coverage, the bound's ratio to the true
error, against the global Cauchy-Schwarz product's, the signed effectivity) and
DIR/target_error_study.csv.

    scripts/target_error_study.py --out results/target_error_study          # about 15 min
    scripts/target_error_study.py --out results/target_error_study --phantom --compare-max   # + about 20 min
    scripts/target_error_study.py --out results/target_error_study --phantom --compare-max --write-doc   # into the docs

--phantom: the phantom insertion (8x4x4 and adaptive, estimates every 10th step) with targets
2 mm ahead of the final tip position and at probes p3 and p1C, against the 32x16x16 run:
median effectivity per target and component and its 10-90 % range over the run.
--compare-max: goal-oriented refinement against the max rule on the energy estimate, on the
static box with body force (interior target): DOFs and wall time to reach the same true error.
"""
import argparse
import csv
import json
import math
import os
import shutil
import subprocess
import sys

from .. import paths
from .runs import write_doc_block

SCENES = ["box_body_force.yaml", "box_end_displacement.yaml"]
GRIDS = [(8, 4, 4), (16, 8, 8), (32, 16, 16), (64, 32, 32)]
RADIUS = 0.00125


def run(tool, scene, out, sets):
    os.makedirs(out, exist_ok=True)
    summary = os.path.join(out, "summary.json")
    if not os.path.exists(summary) or json.load(open(summary)).get("status") != "ok":
        cmd = [tool, "--blas-threads", "2", "run", scene, "--out", out, "--target-error", "-q"]
        for s in sets:
            cmd += ["--set", s]
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return json.load(open(summary))


def richardson(a, b, c):
    """Extrapolation from three values on meshes h, h/2, h/4 (per component), and the rate."""
    out, rates = [], []
    for k in range(3):
        d1, d2 = b[k] - a[k], c[k] - b[k]
        if abs(d2) < 1e-30 or d1 * d2 <= 0:
            out.append(c[k])
            rates.append(float("nan"))
            continue
        r = d1 / d2  # = 2^p
        out.append(c[k] + d2 / (r - 1))
        rates.append(math.log2(r))
    return out, rates


def read_csv(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def pct(v, q):
    v = sorted(v)
    return v[min(len(v) - 1, max(0, int(round(q * (len(v) - 1)))))]


PHANTOM_TARGETS = [("ahead", (0.022, 0.01, 0.01)), ("p3", (0.0075, 0.01, 0.01)), ("p1C", (0.0025, 0.01, 0.0145))]


def phantom(a, md):
    scene = paths.scene("phantom_insertion_8x4x4.yaml")
    targets = "targets=[" + ", ".join("{name: %s, point: [%g, %g, %g], radius: %g}" % (n, p[0], p[1], p[2], RADIUS)
                                       for n, p in PHANTOM_TARGETS) + "]"
    runs = {}
    for label, sets in [("32x16x16", ["tissue.grid.cells=[32,16,16]"]), ("8x4x4", []),
                        ("adaptive", ["adaptivity={estimator: spr, marking: max, theta: 0.3, max_level: 2, max_dofs: 6000, "
                                      "every_steps: 20, coarsen: {enabled: true, theta_coarsen: 0.1, after: 3}}"])]:
        out = os.path.join(a.out, "phantom", label)
        os.makedirs(out, exist_ok=True)
        if not (os.path.exists(os.path.join(out, "summary.json")) and json.load(open(os.path.join(out, "summary.json")))["status"] == "ok"):
            cmd = [a.tool, "run", scene, "--out", out, "--target-error", "--target-error-every", "10", "-q", "--set", targets]
            for x in sets:
                cmd += ["--set", x]
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        runs[label] = {int(r["step"]): r for r in read_csv(os.path.join(out, "timeseries.csv"))}
    ref = runs["32x16x16"]
    summary = phantom_summary(runs)
    md.append("\n## Phantom insertion\n")
    md.append("Targets 2 mm ahead of the final tip (x = 22 mm on the axis) and at probes p3, p1C, regularised over "
              "%.2f mm; estimates every 10th step against the difference to the 32x16x16 run; effectivity over the "
              "steps whose true error is above 1 %% of its largest over the run (median, 10 %%-90 %% range)." % (1e3 * RADIUS))
    md.append("\n| mesh | target | component | steps compared | median effectivity | 10 % | 90 % | bound covers |")
    md.append("|---|---|---|---|---|---|---|---|")
    for label in ("8x4x4", "adaptive"):
        run = runs[label]
        for name, _ in PHANTOM_TARGETS:
            for comp in "xyz":
                pairs = []
                for step, r in run.items():
                    if step % 10 or step not in ref:
                        continue
                    try:
                        qh, qr = float(r["%s_qoi_%s" % (name, comp)]), float(ref[step]["%s_qoi_%s" % (name, comp)])
                        est = float(r["%s_err_%s" % (name, comp)])
                        bound = float(r["%s_err_bound" % name])
                    except (KeyError, ValueError):
                        continue
                    if any(math.isnan(v) for v in (qh, qr, est, bound)):
                        continue
                    pairs.append((qr - qh, est, bound))
                if not pairs:
                    continue
                big = max(abs(e) for e, _, _ in pairs)
                sel = [(e, est, b) for e, est, b in pairs if abs(e) > 0.01 * big and big > 0]
                if len(sel) < 5:
                    continue
                effs = [est / e for e, est, _ in sel]
                cov = sum(1 for e, _, b in sel if b >= abs(e))
                md.append("| %s | %s | %s | %d | %.2f | %.2f | %.2f | %d %% |" % (
                    label, name, comp, len(sel), pct(effs, 0.5), pct(effs, 0.1), pct(effs, 0.9), 100 * cov // len(sel)))
    plot_phantom(runs, os.path.join(a.out, "phantom_error_vs_step.png"))
    md.append("\nFigure: `phantom_error_vs_step.png` (the norm of the true error, of the signed estimate, and the bound "
              "against step, per target, on 8x4x4 and adaptive).")
    return summary


def estimated_steps(runs, label, name):
    """Target `name`'s estimated steps (every 10th) of run `label` that the reference run has, in
    order: (step, Q_h, Q_ref, the signed estimate, the bound); steps with a missing or NaN value
    left out."""
    ref = runs["32x16x16"]
    for step, r in sorted(runs[label].items()):
        if step % 10 or step not in ref:
            continue
        try:
            q = [float(r["%s_qoi_%s" % (name, c)]) for c in "xyz"]
            qr = [float(ref[step]["%s_qoi_%s" % (name, c)]) for c in "xyz"]
            est = [float(r["%s_err_%s" % (name, c)]) for c in "xyz"]
            b = float(r["%s_err_bound" % name])
        except (KeyError, ValueError):
            continue
        if not any(math.isnan(v) for v in q + qr + est + [b]):
            yield step, q, qr, est, b


def phantom_summary(runs):
    """Per mesh, over every target and estimated step whose true error norm is above 1 % of that
    target's largest over the run: coverage, bound / true error (median), and the signed
    estimate's effectivity (median over the moving components' steps)."""
    out = []
    for label in ("8x4x4", "adaptive"):
        ratios, effs, covered = [], [], 0
        for name, _ in PHANTOM_TARGETS:
            pairs = [([x - y for x, y in zip(qr, q)], est, b) for _, q, qr, est, b in estimated_steps(runs, label, name)]
            if not pairs:
                continue
            big = max(math.hypot(*e) for e, _, _ in pairs)
            bigk = [max(abs(e[k]) for e, _, _ in pairs) for k in range(3)]
            for e, est, b in pairs:
                n = math.hypot(*e)
                if n <= 0.01 * big:
                    continue
                ratios.append(b / n)
                covered += b >= n
                for k in range(3):
                    if bigk[k] > 0.1 * big and abs(e[k]) > 0.01 * bigk[k]:
                        effs.append(est[k] / e[k])
        if ratios:
            out.append({"case": "phantom insertion, %s" % label, "compared": len(ratios),
                        "covered_pct": 100.0 * covered / len(ratios), "bound_over_error_median": pct(ratios, 0.5),
                        "bound_over_error_min": min(ratios), "bound_over_error_max": max(ratios),
                        "effectivity_median": pct(effs, 0.5) if effs else float("nan")})
    return out


def summary_markdown(rows, phantom_rows):
    """The study's summary per case: what doc/verification.md shows."""
    lines = ["| case | compared | bound covers | bound / true error: median (min-max) | global product / true error: median "
             "| signed effectivity: median (in [0.5, 2]) |", "|---|---|---|---|---|---|"]
    for scene in SCENES:
        name = scene[:-5]
        sel = [r for r in rows if r["scene"] == name]
        if not sel:
            continue
        # one row per target and mesh for the bound (the norm), per component for the estimate
        cases = {(r["target"], r["mesh"]): r for r in sel}.values()
        sharp = sorted(r["sharpness"] for r in cases)
        gsharp = sorted(r["global_sharpness"] for r in cases)
        effs = sorted(r["effectivity"] for r in sel)
        lines.append("| static, %s (%d targets x 4 meshes) | %d | %d %% | %.2f (%.2f-%.2f) | %.1f | %.2f (%d of %d) |" % (
            name, len({r["target"] for r in sel}), len(sharp), round(100 * sum(1 for r in cases if r["covered"]) / len(sharp)),
            pct(sharp, 0.5), sharp[0], sharp[-1], pct(gsharp, 0.5), pct(effs, 0.5),
            sum(1 for e in effs if 0.5 <= e <= 2), len(effs)))
    for p in phantom_rows:
        lines.append("| %s (steps x targets) | %d | %.0f %% | %.2f (%.2f-%.2f) | – | %.2f |" % (
            p["case"], p["compared"], p["covered_pct"], p["bound_over_error_median"], p["bound_over_error_min"],
            p["bound_over_error_max"], p["effectivity_median"]))
    return "\n".join(lines) + "\n"


def plot_phantom(runs, path):
    """Per target (a panel each) and mesh (a colour each): |Q_ref - Q_h|, |estimate| and the bound
    against step, at the estimated steps (every 10th)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(PHANTOM_TARGETS), figsize=(15, 4.4), sharey=True)
    for ax, (name, _) in zip(axes, PHANTOM_TARGETS):
        for label, color in (("8x4x4", "C0"), ("adaptive", "C1")):
            steps, true, est, bound = [], [], [], []
            for step, q, qr, e, b in estimated_steps(runs, label, name):
                steps.append(step)
                true.append(1e6 * math.dist(q, qr))
                est.append(1e6 * math.sqrt(sum(x * x for x in e)))
                bound.append(1e6 * b)
            ax.semilogy(steps, true, color=color, lw=1.2, label="%s: true error (vs 32x16x16)" % label)
            ax.semilogy(steps, est, color=color, lw=0.8, ls=":", label="%s: |signed estimate|" % label)
            ax.semilogy(steps, bound, color=color, lw=1, ls="--", label="%s: bound" % label)
        ax.set_title("target %s" % name)
        ax.set_xlabel("step (dt 1 ms)")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("error of the regularised displacement [um]")
    axes[0].legend(fontsize=7)
    fig.suptitle("Phantom insertion: goal-oriented estimate and bound against the true error")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print("wrote", path)


def compare_max(a, md, path):
    """Goal-oriented refinement against the max rule on the energy estimate (interior target)."""
    def qz(out):
        return json.load(open(os.path.join(out, "summary.json")))

    ref_runs = [qz(os.path.join(a.out, "box_body_force", g)) for g in ("16x8x8", "32x16x16", "64x32x32")]
    ref, _ = richardson(*[r["targets"]["interior"]["qoi"] for r in ref_runs])
    radius = ["targets.%d.radius=%g" % (j, RADIUS) for j in range(3)]
    coarse = run(a.tool, path, os.path.join(a.out, "compare", "coarse"), ["tissue.grid.cells=[8,4,4]"] + radius)
    tol = 0.5 * coarse["targets"]["interior"]["error_bound"]
    rows = []
    goal = run(a.tool, path, os.path.join(a.out, "compare", "goal"), radius + [
        "adaptivity={estimator: goal, goal: {targets: [interior], tolerance: %g}, marking: max, theta: 0.3, "
        "max_level: 3, every_steps: 1}" % tol])
    rows.append(("goal (tolerance %.2e m)" % tol, goal))
    for budget in (1500, 3000, 6000, 12000, 24000, 48000):
        s = run(a.tool, path, os.path.join(a.out, "compare", "max_%d" % budget), radius + [
            "adaptivity={estimator: spr, marking: max, theta: 0.3, max_level: 3, max_dofs: %d, every_steps: 1}" % budget])
        rows.append(("max rule, budget %d DOFs" % budget, s))
    table = ["| refinement | DOFs | wall [s] | true error \\|Q_ref − Q_h\\| [m] | bound [m] |", "|---|---|---|---|---|"]
    for label, s in rows:
        t = s["targets"]["interior"]
        err = math.sqrt(sum((r - h) ** 2 for r, h in zip(ref, t["qoi"])))
        table.append("| %s | %d | %.2f | %.3e | %.3e |" % (label, s["tissue"]["dofs"], s["wall_time_s"], err, t["error_bound"]))
    md.append("\n## Goal-oriented refinement against the max rule\n")
    md.append("Static box with body force, interior target; the same true error is the goal run's. Reference as above.\n")
    md.extend(table)
    return "\n".join(table) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=paths.results_dir("target_error_study"))
    ap.add_argument("--tool", default=paths.tool())
    ap.add_argument("--phantom", action="store_true", help="also the phantom insertion part")
    ap.add_argument("--compare-max", action="store_true", help="also goal-oriented against max-rule refinement")
    ap.add_argument("--only-phantom", action="store_true", help="the phantom insertion part alone (and its figure)")
    ap.add_argument("--write-doc", action="store_true",
                    help="with --phantom --compare-max: the summary and the comparison into doc/verification.md's "
                         "block, the figure into doc/")
    a = ap.parse_args()
    if a.only_phantom:
        md = ["# Goal-oriented target-error estimate: the phantom insertion\n",
              "Command: `scripts/target_error_study.py --out %s --only-phantom`\n" % a.out]
        summary = phantom(a, md)
        md.append("\n" + summary_markdown([], summary))
        with open(os.path.join(a.out, "target_error_phantom.md"), "w") as f:
            f.write("\n".join(md) + "\n")
        print("\n".join(md))
        return 0
    data = os.path.join(paths.share_dir(), "test", "data", "target_error")
    rows, md = [], ["# Goal-oriented target-error estimate: verification\n",
                    "Static boxes of `test/data/target_error/`, regularised point of radius %.2f mm; reference: "
                    "Richardson extrapolation from 16x8x8, 32x16x16, 64x32x32 (rate fitted per component), "
                    "error bar: its difference from the extrapolation of 8x4x4, 16x8x8, 32x16x16. "
                    "Effectivity = estimate / true error, for components above 1 %% of the largest.\n" % (1e3 * RADIUS),
                    "Command: `scripts/target_error_study.py --out %s`\n" % a.out]
    for scene in SCENES:
        path = os.path.join(data, scene)
        name = scene[:-5]
        targets = None
        uniform = {}
        for g in GRIDS:
            cells = "[%d,%d,%d]" % g
            sets = ["tissue.grid.cells=" + cells] + ["targets.%d.radius=%g" % (i, RADIUS) for i in range(3)]
            s = run(a.tool, path, os.path.join(a.out, name, "%dx%dx%d" % g), sets)
            uniform[g] = s
            targets = list(s["targets"].keys())
        adaptive = {}
        for i, t in enumerate(targets):
            sets = ["tissue.grid.cells=[8,4,4]", "time.duration=6"] + ["targets.%d.radius=%g" % (j, RADIUS) for j in range(3)]
            sets += ["adaptivity={estimator: goal, goal: {targets: [%s], tolerance: 1.0e-9}, marking: max, theta: 0.3, "
                     "max_level: 2, every_steps: 1}" % t]
            adaptive[t] = run(a.tool, path, os.path.join(a.out, name, "adaptive_" + t), sets)
        md.append("\n## %s\n" % name)
        md.append("| target | mesh | DOFs | component | Q_h [m] | true error [m] | estimate [m] | effectivity | bound [m] | |e| [m] | "
                  "bound / |e| | global product / |e| | covered |")
        md.append("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
        for t in targets:
            q = {g: uniform[g]["targets"][t]["qoi"] for g in GRIDS}
            ref, rates = richardson(q[GRIDS[1]], q[GRIDS[2]], q[GRIDS[3]])
            ref_coarse, _ = richardson(q[GRIDS[0]], q[GRIDS[1]], q[GRIDS[2]])
            bar = [abs(x - y) for x, y in zip(ref, ref_coarse)]
            cases = [("%dx%dx%d" % g, uniform[g]) for g in GRIDS[:3]] + [("adaptive", adaptive[t])]
            for label, s in cases:
                tt = s["targets"][t]
                qh, est, bound = tt["qoi"], tt["error_estimate"], tt["error_bound"]
                gbound = tt.get("error_bound_global", float("nan"))
                err = [r - h for r, h in zip(ref, qh)]
                enorm = math.sqrt(sum(e * e for e in err))
                big = max(abs(e) for e in err)
                dofs = s["tissue"]["dofs"]
                for k, comp in enumerate("xyz"):
                    if abs(err[k]) < 0.01 * big or abs(err[k]) < 3 * bar[k]:
                        continue
                    eff = est[k] / err[k]
                    rows.append({"scene": name, "target": t, "mesh": label, "dofs": dofs, "component": comp, "qoi": qh[k],
                                 "true_error": err[k], "estimate": est[k], "effectivity": eff, "bound": bound,
                                 "error_norm": enorm, "covered": bound >= enorm, "reference": ref[k],
                                 "reference_bar": bar[k], "rate": rates[k], "sharpness": bound / enorm,
                                 "global_sharpness": gbound / enorm})
                    md.append("| %s | %s | %d | %s | %.5e | %.3e | %.3e | %.2f | %.3e | %.3e | %.1f | %.1f | %s |" % (
                        t, label, dofs, comp, qh[k], err[k], est[k], eff, bound, enorm, bound / enorm, gbound / enorm,
                        "yes" if bound >= enorm else "NO"))
    effs = [r["effectivity"] for r in rows]
    cov = sum(1 for r in rows if r["covered"])
    md.append("\n%d cases: effectivity %.2f .. %.2f (median %.2f), %d in [0.5, 2]; the bound covers the true error in %d "
              "of %d." % (len(rows), min(effs), max(effs), sorted(effs)[len(effs) // 2],
                          sum(1 for e in effs if 0.5 <= e <= 2), cov, len(rows)))
    sharp = sorted(r["sharpness"] for r in rows)
    gsharp = sorted(r["global_sharpness"] for r in rows)
    md.append("Bound / true error norm: %.2f .. %.2f (median %.2f), %d in [1, 4]; the global product's: %.1f .. %.1f "
              "(median %.1f)." % (sharp[0], sharp[-1], sharp[len(sharp) // 2], sum(1 for v in sharp if 1 <= v <= 4),
                                  gsharp[0], gsharp[-1], gsharp[len(gsharp) // 2]))
    compare = compare_max(a, md, os.path.join(data, "box_body_force.yaml")) if a.compare_max else None
    phantom_rows = phantom(a, md) if a.phantom else []
    summary = summary_markdown(rows, phantom_rows)
    md.append("\n## Summary\n\n" + summary)
    os.makedirs(a.out, exist_ok=True)
    with open(os.path.join(a.out, "target_error_study.csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0].keys()))
        w.writeheader()
        w.writerows(rows)
    with open(os.path.join(a.out, "target_error_study.md"), "w") as f:
        f.write("\n".join(md) + "\n")
    print("\n".join(md))
    if a.write_doc:
        if not (a.phantom and a.compare_max):
            sys.exit("target_error_study: --write-doc needs --phantom and --compare-max (the doc shows all three parts)")
        doc = summary + "\nGoal-oriented refinement against the max rule on the energy estimate (body-force box, interior " \
            "target; the goal run's tolerance is half its 8×4×4 bound, the max-rule runs stop at a DOF budget; one static " \
            "step each):\n\n" + compare
        write_doc_block("verification.md", "target_error_study", doc,
                        "scripts/target_error_study.py --out %s --phantom --compare-max --write-doc"
                        % os.path.relpath(a.out, paths.share_dir()))
        shutil.copy(os.path.join(a.out, "phantom_error_vs_step.png"),
                    os.path.join(paths.share_dir(), "doc", "target_error_phantom.png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Twin experiments for the online estimation (`needle_sim run SCENE --data FILE --assimilate
KEYS`, doc/calibration.md "Assimilation"; issue #41's verification).

A "patient" run with hidden values makes the measured holder force: every 5th step of its
`<needle>_axial_force` plus Gaussian noise. The estimator, started from the scene's nominal
values, recovers the hidden values causally. Reported per run: the estimate at the end and
halfway through the record (relative error, error in its standard deviations); over the
phantom's seeds, the share of estimates within 2 standard deviations (calibrated uncertainty:
about 95 % expected, at least 80 % asked). The DBS twin also follows the STN: its predicted
end position against the patient's, and how often the patient's lies inside the published
95 % ellipsoid (chi-square, 3 degrees of freedom, 7.81) after the estimate has converged.
The target twin (`--target`) measures a target beside the phantom's path every 0.1 s (an
image) at the patient's position plus an offset the model cannot know (drawn per seed, up to
1 mm per axis), beside the force: the estimator's predicted end position (the model's plus the
estimated offset) against the truth, inside the 95 % ellipsoid at how many checkpoints.

    scripts/assimilation_study.py --out /tmp/assim                 # phantom, 10 seeds (~10 min)
    scripts/assimilation_study.py --out /tmp/assim --dbs           # + the DBS twin (~30 min more)
    scripts/assimilation_study.py --out /tmp/assim --target      # + the target twin (~5 min more)
    scripts/assimilation_study.py --out /tmp/assim --dbs --target --write-doc
"""
import argparse
import concurrent.futures
import csv
import json
import math
import os
import random
import shlex
import subprocess
import sys

from .. import paths
from .runs import write_doc_block

PHANTOM = "phantom_insertion_8x4x4.yaml"
PHANTOM_SETS = ["time.dt=0.002"]
DBS = "dbs_coarse.yaml"


REUSE = False  # --reuse: runs whose outputs exist are read, not made again


def patient(tool, scene, sets, hidden, needle, noise, seed, out):
    """The hidden truth's run and its noisy force record out/force.csv."""
    truth = os.path.join(out, "truth")
    if REUSE and os.path.exists(os.path.join(out, "force.csv")):
        return list(csv.DictReader(open(os.path.join(truth, "timeseries.csv"))))
    cmd = [tool, "run", paths.scene(scene), "--out", truth, "--quiet"]
    for s in sets + ["%s=%.17g" % kv for kv in hidden.items()]:
        cmd += ["--set", s]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    rows = list(csv.DictReader(open(os.path.join(truth, "timeseries.csv"))))
    rng = random.Random(seed)
    with open(os.path.join(out, "force.csv"), "w") as f:
        f.write("t,axial_force\n")
        for r in rows[4::5]:
            f.write("%s,%.9g\n" % (r["t"], float(r["%s_axial_force" % needle]) + rng.gauss(0.0, noise)))
    return rows


def assimilate(tool, scene, sets, keys, starts, noise, every, out):
    cmd = [tool, "run", paths.scene(scene), "--out", os.path.join(out, "estimate"), "--quiet",
           "--data", os.path.join(out, "force.csv"), "--assimilate", ",".join(keys), "--noise", "%g" % noise]
    if every:
        cmd += ["--assimilate-every", "%g" % every]
    for s in sets:
        cmd += ["--set", s]
    for k, v in starts.items():
        cmd += ["--start", "%s=%g" % (k, v)]
    if not (REUSE and os.path.exists(os.path.join(out, "estimate", "assimilation.csv"))):
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    cps = list(csv.DictReader(open(os.path.join(out, "estimate", "assimilation.csv"))))
    summary = json.load(open(os.path.join(out, "estimate", "summary.json")))
    return cps, summary, cmd


def judge(cps, hidden, t_half):
    """Per key: relative error and error in standard deviations at the end and halfway."""
    end = cps[-1]
    half = [c for c in cps if float(c["t"]) <= t_half + 1e-9]
    half = half[-1] if half else None
    out = {}
    for k, v in hidden.items():
        e, s = float(end[k]), float(end[k + "_std"])
        out[k] = {"end": e, "end_std": s, "end_rel": (e - v) / v, "end_z": (e - v) / s if s > 0 else math.inf,
                  "half_rel": (float(half[k]) - v) / v if half else math.nan,
                  "half": float(half[k]) if half else math.nan, "half_std": float(half[k + "_std"]) if half else math.nan,
                  "half_t": float(half["t"]) if half else math.nan}
    return out


def phantom_twin(tool, seed, noise, root):
    rng = random.Random(1000 + seed)
    hidden = {"interaction.cutting_force": round(rng.uniform(0.015, 0.045), 4),
              "interaction.grip_pressure": round(rng.uniform(200.0, 800.0), 1)}
    out = os.path.join(root, "phantom_seed%d" % seed)
    os.makedirs(out, exist_ok=True)
    patient(tool, PHANTOM, PHANTOM_SETS, hidden, "needle", noise, seed, out)
    cps, summary, cmd = assimilate(tool, PHANTOM, PHANTOM_SETS, list(hidden), {"interaction.grip_pressure": 150.0},
                                   noise, 0, out)
    # The insertion (20 mm at 1 cm/s from t = 0.3 s) is half done at 1.3 s.
    return seed, hidden, judge(cps, hidden, 1.3), cmd


TARGET = "targets=[{name: T, point: [0.022, 0.0115, 0.0105], radius: 0.001}]"
TARGET_NOISE = 5e-5  # an image's 50 um per coordinate


def target_twin(tool, seed, noise, root):
    """The phantom with a target beside the path, measured every 0.1 s at the patient's
    position plus a hidden offset; cutting force hidden, the force beside the images."""
    rng = random.Random(2000 + seed)
    hidden = {"interaction.cutting_force": round(rng.uniform(0.015, 0.045), 4)}
    offset = [round(rng.uniform(-1e-3, 1e-3), 6) for _ in range(3)]
    out = os.path.join(root, "target_seed%d" % seed)
    os.makedirs(out, exist_ok=True)
    sets = PHANTOM_SETS + [TARGET]
    rows = patient(tool, PHANTOM, sets, hidden, "needle", noise, seed, out)
    if not (REUSE and os.path.exists(os.path.join(out, "force_target.csv"))):
        rng = random.Random(seed)
        with open(os.path.join(out, "force_target.csv"), "w") as f:
            f.write("t,axial_force,T_x,T_y,T_z\n")
            for i, r in enumerate(rows[4::5]):
                line = "%s,%.9g" % (r["t"], float(r["needle_axial_force"]) + rng.gauss(0.0, noise))
                if i % 10 == 0:
                    line += "".join(",%.9g" % (float(r["T_" + c]) + o + rng.gauss(0.0, TARGET_NOISE))
                                    for c, o in zip("xyz", offset))
                else:
                    line += ",,,"
                f.write(line + "\n")
    cmd = [tool, "run", paths.scene(PHANTOM), "--out", os.path.join(out, "estimate"), "--quiet",
           "--data", os.path.join(out, "force_target.csv"), "--assimilate", ",".join(hidden),
           "--noise", "%g" % noise, "--target-noise", "%g" % TARGET_NOISE]
    for x in sets:
        cmd += ["--set", x]
    if not (REUSE and os.path.exists(os.path.join(out, "estimate", "assimilation.csv"))):
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    cps = list(csv.DictReader(open(os.path.join(out, "estimate", "assimilation.csv"))))
    truth = [float(rows[-1]["T_" + c]) + o for c, o in zip("xyz", offset)]
    per = []
    for c in cps:
        p = [float(c["T_end_" + x]) for x in "xyz"]
        sd = [float(c["T_end_std_" + x]) for x in "xyz"]
        # The covariance is diagonal here to within the parameters' part (one key, a target
        # that hardly moves): the per-axis deviations give its Mahalanobis distance.
        d2 = sum(((pi - ti) / si) ** 2 for pi, ti, si in zip(p, truth, sd))
        per.append((float(c["t"]), math.dist(p, truth), max(sd), d2))
    return seed, hidden, offset, judge(cps, hidden, 1.3), per, cmd


def dbs_twin(tool, noise, root):
    hidden = {"tissue.material.young": 3000.0, "interaction.grip_pressure": 600.0}
    out = os.path.join(root, "dbs")
    os.makedirs(out, exist_ok=True)
    rows = patient(tool, DBS, [], hidden, "cannula", noise, 1, out)
    cps, summary, cmd = assimilate(tool, DBS, [], list(hidden), {}, noise, 4.5, out)
    truth_end = [float(rows[-1]["STN_L_%s" % c]) for c in "xyz"]
    stn = []
    for c in cps:
        p = [float(c["STN_L_end_%s" % x]) for x in "xyz"]
        sd = [float(c["STN_L_end_std_%s" % x]) for x in "xyz"]
        err = math.dist(p, truth_end)
        stn.append((float(c["t"]), err, sd))
    cov = summary["assimilation"]["targets"]["STN_L"]["end_covariance"]
    # The hidden values' own RMS residual over each checkpoint's window: the noise they were
    # drawn with. A fit with a larger one is not the best fit (a local minimum).
    import numpy as np
    tt = np.array([float(r["t"]) for r in rows])
    ff = np.array([float(r["cannula_axial_force"]) for r in rows])
    rec = list(csv.DictReader(open(os.path.join(out, "force.csv"))))
    mt = np.array([float(r["t"]) for r in rec])
    res = np.array([float(r["axial_force"]) for r in rec]) - np.interp(mt, tt, ff)
    truth_rms = [float(np.sqrt(np.mean(res[mt <= float(c["t"]) + 1e-9] ** 2))) for c in cps]
    return hidden, judge(cps, hidden, 9.0), stn, cps, cmd, truth_end, cov, truth_rms


def dbs_landscape(tool, noise_root, fit, hidden, jobs, points=11):
    """The DBS record's RMS residual along the segment from the final fit to the hidden values
    (a fraction a of the way): where a local search could not cross. Per point also the
    largest residual and when the cannula's force peaks (the grip's release during the
    withdrawal)."""
    import numpy as np
    out = os.path.join(noise_root, "dbs", "landscape")
    os.makedirs(out, exist_ok=True)
    rec = list(csv.DictReader(open(os.path.join(noise_root, "dbs", "force.csv"))))
    mt = np.array([float(r["t"]) for r in rec])
    mf = np.array([float(r["axial_force"]) for r in rec])
    keys = list(hidden)

    def point(i):
        a = i / (points - 1)
        v = [f + a * (hidden[k] - f) for k, f in zip(keys, fit)]
        d = os.path.join(out, "a%02d" % i)
        if not (REUSE and os.path.exists(os.path.join(d, "timeseries.csv"))):
            cmd = [tool, "run", paths.scene(DBS), "--out", d, "--quiet"]
            for k, x in zip(keys, v):
                cmd += ["--set", "%s=%.17g" % (k, x)]
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        rows = list(csv.DictReader(open(os.path.join(d, "timeseries.csv"))))
        tt = np.array([float(r["t"]) for r in rows])
        ff = np.array([float(r["cannula_axial_force"]) for r in rows])
        res = mf - np.interp(mt, tt, ff)
        return a, v, float(np.sqrt(np.mean(res ** 2))), float(np.abs(res).max()), float(tt[np.argmax(ff)]), float(ff.max())

    with concurrent.futures.ThreadPoolExecutor(jobs) as ex:
        return list(ex.map(point, range(points)))


def mahalanobis2(d, cov):
    """(d^T C^+ d over C's range, |d| outside it [m], C's rank). With fewer keys than 3 the
    targets' covariance G Cov G^T has rank below 3: a distance off its range is not a number of
    standard deviations, and is reported apart."""
    import numpy as np
    c = np.array([[math.inf if v is None else v for v in cov[3 * i:3 * i + 3]] for i in range(3)])
    if not np.all(np.isfinite(c)):
        return math.inf, math.inf, 3
    w, v = np.linalg.eigh(0.5 * (c + c.T))
    keep = w > 1e-9 * max(w.max(), 0.0)
    dv = v.T @ np.array(d)
    inside = float(np.sum(dv[keep] ** 2 / w[keep])) if keep.any() else 0.0
    return inside, float(np.linalg.norm(dv[~keep])), int(keep.sum())


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--tool", default=None)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--noise", type=float, default=5e-4, help="the phantom's force noise [N] (default 0.5 mN)")
    ap.add_argument("--dbs", action="store_true", help="also the DBS twin (young and grip from the cannula's force)")
    ap.add_argument("--dbs-noise", type=float, default=2e-3, help="the DBS cannula force's noise [N] (default 2 mN)")
    ap.add_argument("--target", action="store_true", help="also the target twin (a measured target with a hidden offset)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--write-doc", action="store_true", help="write the tables into doc/benchmarks.md")
    ap.add_argument("--reuse", action="store_true", help="read the runs already in --out instead of making them again")
    a = ap.parse_args()
    global REUSE
    REUSE = a.reuse
    tool = a.tool or paths.tool()
    os.makedirs(a.out, exist_ok=True)
    with concurrent.futures.ThreadPoolExecutor(a.jobs) as ex:
        results = sorted(ex.map(lambda s: phantom_twin(tool, s, a.noise, a.out), range(1, a.seeds + 1)))
    lines = ["| seed | key | hidden | end: estimate ± std | error | in std | halfway: estimate ± std | error |",
             "|---|---|---|---|---|---|---|---|"]
    within2 = within3 = total = 0
    worst_end = worst_half = 0.0
    for seed, hidden, j, _ in results:
        for k, v in hidden.items():
            r = j[k]
            total += 1
            within2 += abs(r["end_z"]) <= 2
            within3 += abs(r["end_z"]) <= 3
            worst_end = max(worst_end, abs(r["end_rel"]))
            worst_half = max(worst_half, abs(r["half_rel"]))
            lines.append("| %d | `%s` | %.6g | %.6g ± %.2g | %+.2f %% | %+.2f | %.4g ± %.2g | %+.1f %% |" % (
                seed, k, v, r["end"], r["end_std"], 100 * r["end_rel"], r["end_z"], r["half"], r["half_std"],
                100 * r["half_rel"]))
    cmd = results[0][3]
    shown = " ".join(shlex.quote(c if not c.startswith(a.out) else "DIR" + c[len(a.out):]) for c in cmd)
    shown = shown.replace(tool, "devel/lib/needle_sim/needle_sim").replace(paths.scene(PHANTOM), "config/scenes/" + PHANTOM)
    md = ("Phantom insertion (8×4×4, 2 ms steps), cutting force and grip pressure hidden (drawn per seed from "
          "15–45 mN and 200–800 Pa), force noise %.1f mN, every 5th step; the estimator from the scene's 20 mN and "
          "150 Pa, a checkpoint every tenth of the record. One seed's command (DIR/force.csv from the patient run):\n\n"
          "```bash\n%s\n```\n\n%s\n\n"
          "Within 2 standard deviations at the end: **%d of %d** (%.0f %%); within 3: %d of %d. Largest error at the "
          "end %.2f %%; halfway through the insertion (t = 1.3 s: the estimate of the checkpoint before, t = %.2f s) "
          "%.1f %%.\n" % (
              1e3 * a.noise, shown, "\n".join(lines), within2, total, 100.0 * within2 / total, within3, total,
              100 * worst_end, results[0][2][list(results[0][1])[0]]["half_t"], 100 * worst_half))
    if a.target:
        with concurrent.futures.ThreadPoolExecutor(a.jobs) as ex:
            tres = sorted(ex.map(lambda s: target_twin(tool, s, a.noise, a.out), range(1, a.seeds + 1)))
        tl = ["| seed | offset [mm] | cutting: hidden, estimate ± std | checkpoints | first: error, std [mm] | "
              "end: error, std [mm] | inside the 95 % ellipsoid (from the 2nd) |", "|---|---|---|---|---|---|---|"]
        inside = judged = 0
        for seed, hidden, offset, j, per, _ in tres:
            r = j["interaction.cutting_force"]
            later = per[1:]
            n_in = sum(d2 <= 7.81 for _, _, _, d2 in later)
            inside += n_in
            judged += len(later)
            tl.append("| %d | %s | %.4g, %.5g ± %.2g | %d | %.4f, %.4f | %.4f, %.4f | %d of %d |" % (
                seed, ", ".join("%+.3f" % (1e3 * o) for o in offset), hidden["interaction.cutting_force"], r["end"],
                r["end_std"], len(per), 1e3 * per[0][1], 1e3 * per[0][2], 1e3 * per[-1][1], 1e3 * per[-1][2], n_in,
                len(later)))
        tcmd = tres[0][5]
        tshown = " ".join(shlex.quote(c if not c.startswith(a.out) else "DIR" + c[len(a.out):]) for c in tcmd)
        tshown = tshown.replace(tool, "devel/lib/needle_sim/needle_sim").replace(paths.scene(PHANTOM), "config/scenes/" + PHANTOM)
        md += ("\nA measured target (`--target`): the phantom with a target 1.5 mm beside the path, measured every 0.1 s "
               "with %.0f µm of noise per coordinate at the patient's position plus a hidden offset (drawn per seed, up "
               "to 1 mm per axis), the force (%.1f mN) beside it; the cutting force hidden. Error: the predicted end "
               "position (the model's plus the estimated offset) against the patient's plus the offset; std: the largest "
               "axis's. One seed's command:\n\n```bash\n%s\n```\n\n%s\n\nThe truth inside the published 95 %% "
               "ellipsoid (chi-square, 3 degrees of freedom, 7.81) at **%d of %d** checkpoints after the first "
               "(%.0f %%).\n" % (1e6 * TARGET_NOISE, 1e3 * a.noise, tshown, "\n".join(tl), inside, judged,
                                  100.0 * inside / max(judged, 1)))
    if a.dbs:
        hidden, j, stn, cps, dcmd, truth_end, cov, truth_rms = dbs_twin(tool, a.dbs_noise, a.out)
        dl = ["| key | nominal | hidden | estimate ± std | error | in std | at 9 s |", "|---|---|---|---|---|---|---|"]
        nominal = {"tissue.material.young": 2007.0, "interaction.grip_pressure": 800.0}
        for k, v in hidden.items():
            r = j[k]
            dl.append("| `%s` | %g | %g | %.6g ± %.2g | %+.2f %% | %+.2f | %+.1f %% |" % (
                k, nominal[k], v, r["end"], r["end_std"], 100 * r["end_rel"], r["end_z"], 100 * r["half_rel"]))
        sl = ["| checkpoint t [s] | young ± std | grip ± std | RMS residual mN | the hidden values' RMS residual mN "
              "| consistent | STN_L end: predicted − patient [mm] | predicted std x, y, z [mm] |",
              "|---|---|---|---|---|---|---|---|"]
        for (t, err, sd), c, tr in zip(stn, cps, truth_rms):
            sl.append("| %.2f | %.1f ± %.2g | %.1f ± %.2g | %.2f | %.2f | %s | %.4f | %s |" % (
                t, float(c["tissue.material.young"]), float(c["tissue.material.young_std"]),
                float(c["interaction.grip_pressure"]), float(c["interaction.grip_pressure_std"]),
                1e3 * float(c["rms_residual"]), 1e3 * tr, "yes" if c["consistent"] == "1" else "**no**", 1e3 * err,
                ", ".join("%.4f" % (1e3 * s) for s in sd)))
        last = [float(cps[-1]["STN_L_end_%s" % x]) for x in "xyz"]
        d2, off, rank = mahalanobis2([p - q for p, q in zip(last, truth_end)], cov)
        if not math.isfinite(d2):
            maha = "the STN's published covariance is not finite (a key not determined)"
        elif rank == 3:
            maha = ("the patient's STN end position is %.1f Mahalanobis units from the prediction (95 %% ellipsoid: 2.80)"
                    % math.sqrt(d2))
        else:
            maha = ("the STN's published covariance has rank %d (from %d keys): within its range the patient's STN end "
                    "position is %.1f standard deviations from the prediction, and %.4f mm off that range, where the "
                    "covariance says nothing" % (rank, len(hidden), math.sqrt(d2), 1e3 * off))
        dshown = " ".join(shlex.quote(c if not c.startswith(a.out) else "DIR" + c[len(a.out):]) for c in dcmd)
        dshown = dshown.replace(tool, "devel/lib/needle_sim/needle_sim").replace(paths.scene(DBS), "config/scenes/" + DBS)
        md += ("\nDBS (dbs_coarse, cannula force, noise %.1f mN), tissue stiffness and grip hidden:\n\n```bash\n%s\n```\n\n"
               "%s\n\n%s\n\nAt the end %s.\n" % (1e3 * a.dbs_noise, dshown, "\n".join(dl), "\n".join(sl), maha))
        fit = [float(cps[-1][k]) for k in hidden]
        ll = ["| a | young | grip | RMS residual mN | largest residual mN | cannula force's peak: t [s], N |",
              "|---|---|---|---|---|---|"]
        for av, v, rms, worst, tpeak, fpeak in dbs_landscape(tool, a.out, fit, hidden, a.jobs):
            ll.append("| %.1f | %.3f | %.3f | %.2f | %.1f | %.2f, %.2f |" % (av, v[0], v[1], 1e3 * rms, 1e3 * worst, tpeak, fpeak))
        md += ("\nThe record's RMS residual along the segment from the final estimate (a = 0) to the hidden values "
               "(a = 1), the scene run at each point (DIR/dbs/landscape):\n\n%s\n" % "\n".join(ll))
    with open(os.path.join(a.out, "table.md"), "w") as f:
        f.write(md)
    print(md)
    if a.write_doc:
        write_doc_block("benchmarks.md", "assimilation", md,
                        "scripts/assimilation_study.py --out DIR%s%s --write-doc" % (" --dbs" if a.dbs else "",
                                                                                    " --target" if a.target else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())

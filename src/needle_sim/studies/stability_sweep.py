"""Stability sweep (issue #8): the phantom needle insertion run with one parameter at a time
pushed across its range, around the paper's values (8x4x4 grid, E = 10 MPa, nu = 0.4, needle
E = 50 MPa, dt = 1 ms, 10 mm/s, friction 0.05, puncture 0.05 N). Each run inserts the needle
13 mm from 3 mm in front of the block, then holds it still for 0.3 s. A run passes when

  - the tool finishes (no NaN/Inf, no divergence: exit status 0; 3 is a detected failure),
  - the energy is bounded: with the needle held, the kinetic energy of the last 0.15 s stays
    below that of the first 0.15 s of the hold (no growth without input),
  - the constraint solve converged at every step (no unconverged step in summary.json, and
    the largest residual reported <= 1e-6),
  - no element is inverted at the end (inverted elements are reported by the run),
  - the needle never ends up inside the tissue unpunctured (the tip passing through the
    surface without a puncture event is a contact failure),

and reports the SPR estimate's relative error (eta / energy norm) at the end of the
insertion as the error, and what happened physically (punctured or not, tip advance): a
needle that cannot puncture a stiff surface is physics, not instability.
Writes DIR/sweep.csv, DIR/sweep.md (the table) and DIR/stability_map.png (pass/fail and error
per parameter value).

Sample runs:
    scripts/stability_sweep.py --out results/stability          # the full sweep (~40 runs)
    scripts/stability_sweep.py --quick --out /tmp/stability     # the CI subset: the extremes
    scripts/stability_sweep.py --only "tissue young" --out /tmp/soft  # one axis

The tissue-stiffness axis varies the tissue's Young's modulus at the paper's needle (1 kPa,
softer than brain, to the phantom's 10 MPa); the puncture and cutting strengths are scaled
with it (E / 10 MPa, at least 1 mN), so the tissue deforms by about as much as the paper's
phantom before it is punctured rather than being pushed through its clamp. The grip axis
adds the shaft's radial pressure (interaction.grip_pressure), which makes the friction
problem harder (every shaft point carries a bound).
"""
import argparse
import csv
import json
import math
import os
import subprocess
import sys

from .. import paths

SCENE = paths.scene("phantom_insertion_8x4x4.yaml")
TISSUE_E = 1.0e7
DEPTH = 0.013  # commanded advance [m]; the tip starts 3 mm in front of the block
HOLD = 0.3


def motion(speed):
    t = DEPTH / speed
    return t, f"needle.motion=[{{t: 0.0, advance: 0.0}}, {{t: {t:.6g}, advance: {DEPTH}}}]"


def adaptivity(level, coarsen):
    return (f"adaptivity={{estimator: spr, marking: max, theta: 0.3, max_level: {level}, max_dofs: 20000, "
            f"every_steps: 20, coarsen: {{enabled: {'true' if coarsen else 'false'}, theta_coarsen: 0.1, after: 3}}}}")


# Outside the stable envelope (README, Notes): the full sweep runs them and reports how they
# fail; the CI subset (--quick) takes the extremes inside the envelope.
KNOWN_LIMITS = set()


# (parameter, label of a value, value, overrides). Base values are marked in the table.
def sweep(quick, only=None):
    runs = []

    def add(param, values, fn, base):
        if only and only not in param:
            return
        inside = [v for v in values if (param, v) not in KNOWN_LIMITS]
        vs = [inside[0], inside[-1]] if quick else values
        for v in vs:
            runs.append((param, v, fn(v), v == base))

    add("tissue young [Pa]", [1e3, 6e3, 1e5, 1e6, 1e7], lambda E: [
        f"tissue.material.young={E:.6g}", f"interaction.puncture_force={max(0.05 * E / TISSUE_E, 1e-3):.6g}",
        f"interaction.cutting_force={max(0.02 * E / TISSUE_E, 1e-3):.6g}"], 1e7)
    add("grip pressure [Pa]", [0, 100, 500, 2000, 10000], lambda p: [f"interaction.grip_pressure={p}"], 0)
    add("stiffness ratio", [1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7], lambda r: [f"needle.young={r * TISSUE_E:.6g}"], None)
    add("poisson", [0.3, 0.4, 0.45, 0.49, 0.499], lambda nu: [f"tissue.material.poisson={nu}"], 0.4)
    add("dt [s]", [1e-4, 1e-3, 5e-3, 1e-2, 5e-2], lambda dt: [f"time.dt={dt}"], 1e-3)
    add("speed [mm/s]", [1, 3, 10, 30, 100], lambda s: ["@speed", s * 1e-3], 10)
    add("friction", [0.0, 0.05, 0.3, 1.0], lambda f: [f"interaction.friction={f}"], 0.05)
    add("puncture force [N]", [1e-3, 1e-2, 5e-2, 1e-1, 1.0, 10.0],
        lambda f: [f"interaction.puncture_force={f}", f"interaction.cutting_force={f}"], 5e-2)
    add("refinement levels", [0, 1, 2, 3, 4], lambda L: ["@levels", L, True], None)
    add("levels, no coarsening", [1, 2, 3, 4], lambda L: ["@levels", L, False], None)
    return runs


def overrides(spec):
    """Expands a run's spec into --set values and its duration."""
    sets, speed = [], 0.01
    i = 0
    while i < len(spec):
        s = spec[i]
        if s == "@speed":
            speed = spec[i + 1]
            i += 2
        elif s == "@levels":
            if spec[i + 1] > 0:
                sets.append(adaptivity(spec[i + 1], spec[i + 2]))
            i += 3
        else:
            sets.append(s)
            i += 1
    t_end, m = motion(speed)
    return sets + [m, f"time.duration={t_end + HOLD:.6g}"], t_end


def judge(run_dir, rc, t_end):
    out = {"status": "failed" if rc else "ok", "reason": "", "eta_rel": math.nan, "ke_growth": math.nan,
           "constraint_residual": math.nan, "unconverged_steps": 0, "inverted": 0, "tip_advance_mm": math.nan, "punctured": "", "steps": 0}
    try:
        with open(os.path.join(run_dir, "summary.json")) as f:
            s = json.load(f)
    except OSError:
        out["reason"] = f"no summary (exit {rc})"
        return out
    out["steps"] = s.get("steps", 0)
    if s.get("status") != "ok":
        out["status"] = "failed"
        out["reason"] = s.get("message", "") or f"exit {rc}"
        return out
    out["inverted"] = s.get("tissue", {}).get("inverted_elements", 0)
    inter = s.get("interaction", {})
    out["constraint_residual"] = inter.get("constraint_residual_max", math.nan)
    out["unconverged_steps"] = inter.get("unconverged_steps", 0)
    with open(os.path.join(run_dir, "timeseries.csv"), newline="") as f:
        rows = list(csv.DictReader(f))
    t = [float(r["t"]) for r in rows]
    ke = [float(r["kinetic_energy"]) for r in rows]
    first = [k for ti, k in zip(t, ke) if t_end < ti <= t_end + HOLD / 2]
    last = [k for ti, k in zip(t, ke) if ti > t_end + HOLD / 2]
    at_end = [r for r in rows if float(r["t"]) <= t_end + 1e-9]
    if at_end and "eta_relative" in at_end[-1]:
        out["eta_rel"] = float(at_end[-1]["eta_relative"])
    if first and last:
        out["ke_growth"] = max(last) / max(max(first), 1e-300)
    tipx = [float(r["needle_tip_x"]) for r in rows] if rows and "needle_tip_x" in rows[0] else []
    if tipx:
        out["tip_advance_mm"] = (tipx[-1] - (-0.003)) * 1e3
    states = [r.get("needle_state", "") for r in rows]
    out["punctured"] = "yes" if ("inserted" in states or "punctured" in states) else "no"
    reasons = []
    if not (out["ke_growth"] <= 1.0 or max(last or [0]) < 1e-20):
        reasons.append(f"kinetic energy grew x{out['ke_growth']:.3g} while held")
    if out["unconverged_steps"]:
        reasons.append(f"{out['unconverged_steps']} steps with an unconverged constraint solve")
    if not out["constraint_residual"] <= 1e-6:
        reasons.append(f"constraint residual {out['constraint_residual']:.2e}")
    if out["inverted"]:
        reasons.append(f"{out['inverted']} inverted elements")
    if states and states[-1] == "approaching" and tipx and tipx[-1] > 0.0:
        reasons.append("the tip passed through the surface without a puncture")
    if reasons:
        out["status"] = "failed"
        out["reason"] = "; ".join(reasons)
    return out


def plot(table, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    params = list(dict.fromkeys(r["parameter"] for r in table))
    width = max(sum(1 for r in table if r["parameter"] == p) for p in params)
    fig, ax = plt.subplots(figsize=(1.6 * width + 2.5, 0.65 * len(params) + 1.2))
    for y, p in enumerate(params):
        rows = [r for r in table if r["parameter"] == p]
        for x, r in enumerate(rows):
            ok = r["status"] == "ok"
            ax.add_patch(plt.Rectangle((x, y), 0.95, 0.9, color="#7fc97f" if ok else "#f0027f", alpha=0.85))
            eta = r["eta_rel"]
            txt = f"{r['value']}\n" + ("η %.2g" % eta if isinstance(eta, float) and not math.isnan(eta) else "fail")
            ax.text(x + 0.47, y + 0.45, txt, ha="center", va="center", fontsize=7)
    ax.set_xlim(0, width)
    ax.set_ylim(0, len(params))
    ax.set_yticks([i + 0.45 for i in range(len(params))])
    ax.set_yticklabels(params)
    ax.set_xticks([])
    ax.invert_yaxis()
    ax.set_title("Stability sweep, phantom insertion: green passes (η: relative SPR error after the insertion), red fails")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=paths.results_dir("stability"))
    ap.add_argument("--tool", default=paths.tool())
    ap.add_argument("--quick", action="store_true", help="only the extremes of each range (the CI subset)")
    ap.add_argument("--no-plot", action="store_true")
    ap.add_argument("--only", help="only the axes whose name contains this (e.g. 'tissue young')")
    ap.add_argument("--expect-pass", action="store_true", help="exit 1 unless every run passes")
    args = ap.parse_args()
    if not os.access(args.tool, os.X_OK):
        sys.exit(f"stability_sweep: no needle_sim tool at {args.tool}")
    os.makedirs(args.out, exist_ok=True)
    table = []
    for param, value, spec, base in sweep(args.quick, args.only):
        sets, t_end = overrides(spec)
        name = "".join(c if c.isalnum() else "_" for c in f"{param}_{value}")
        d = os.path.join(args.out, name)
        cmd = [args.tool, "run", SCENE, "--out", d, "--quiet", "--error-estimate"]
        for s in sets:
            cmd += ["--set", s]
        rc = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True).returncode
        j = judge(d, rc, t_end)
        row = {"parameter": param, "value": value, "base": "yes" if base else "", **j}
        table.append(row)
        print(f"{param:>22} = {value:<8} {j['status']:>6}  eta {j['eta_rel']:.3g}  steps {j['steps']}  {j['reason']}",
              flush=True)
    with open(os.path.join(args.out, "sweep.csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(table[0].keys()))
        w.writeheader()
        w.writerows(table)
    with open(os.path.join(args.out, "sweep.md"), "w") as f:
        f.write("| parameter | value | result | relative SPR error at the end of insertion | KE growth while held | constraint residual | punctured | tip advance mm | why it failed |\n")
        f.write("|---|---|---|---|---|---|---|---|---|\n")
        for r in table:
            f.write(f"| {r['parameter']} | {r['value']}{' (paper)' if r['base'] else ''} | {r['status']} | {r['eta_rel']:.3g} | "
                    f"{r['ke_growth']:.3g} | {r['constraint_residual']:.2g} | {r['punctured']} | {r['tip_advance_mm']:.2f} | {r['reason']} |\n")
    if not args.no_plot:
        plot(table, os.path.join(args.out, "stability_map.png"))
    failed = [r for r in table if r["status"] != "ok"]
    print(f"stability_sweep: {len(table) - len(failed)} of {len(table)} runs pass; table in {args.out}/sweep.md")
    if args.expect_pass and failed:
        sys.exit(1)


if __name__ == "__main__":
    main()

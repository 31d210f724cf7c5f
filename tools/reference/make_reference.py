#!/usr/bin/env python3
"""Drive tools/reference/locking_reference (deal.II) and write the reference
values of the volumetric-locking benchmark (issue #37) to
test/data/locking_reference.json.

Runs the tool's `verify` task, then every (benchmark, nu, mesh) run, and
Richardson-extrapolates each quantity from the three finest meshes.

Standard library only. Usage (from the repository root):

    python3 tools/reference/make_reference.py [--build-dir build-reference]
        [--out test/data/locking_reference.json] [--reuse] [--nice 10]

--reuse takes a run's raw output from <build-dir>/runs/ when it is there
(same command line), so an interrupted or re-formatted run does not solve
again.
"""

import argparse
import datetime
import hashlib
import json
import math
import os
import re
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.abspath(os.path.join(HERE, "..", ".."))

NUS_BOX = [0.3, 0.4, 0.45, 0.49, 0.499, 0.4999]
NUS_COOK = [0.3, 0.4999]

# (benchmark key, task, formulation, nus, meshes, solver per mesh).
# The three finest meshes are extrapolated; a coarser mesh, where listed,
# only shows whether the observed order is stable.
BOX_MESHES = [4, 8, 16, 32, 64]
COOK_MESHES = [16, 32, 64, 128, 256]
# displacement Q2 at nu = 0.4999: CG with ML AMG (translations only as near
# null space in deal.II 9.4) needs thousands of iterations (2497 at n = 16).
DISP_MESHES = {0.3: [8, 16, 32], 0.4999: [8, 16, 32]}


def box_solver(n):
    # UMFPACK up to 16x8x8 (30k dofs); MINRES/CG with ML AMG above.
    return "direct" if n <= 16 else "iterative"


def box_args(nu, n, formulation):
    args = ["box", "--nu", repr(nu), "--n", str(n), "--formulation", formulation,
            "--solver", box_solver(n)]
    # n >= 32: the y-symmetric half, the same discrete solution as the full
    # box (`verify` checks it) with half the unknowns; the full box would need
    # ~20 GB at n = 64
    if n >= 32:
        args.append("--half")
    return args


SIG = 10  # significant digits kept in the JSON (iterative runs: ~1e-11)


def r(x, sig=SIG):
    if x is None or not math.isfinite(x):
        return None
    if x == 0.0:
        return 0.0
    return float(f"{x:.{sig - 1}e}")


def richardson(values, ratio=2.0, expected_order=None, order_range=(0.5, 6.0)):
    """Extrapolate from the last three values (coarse -> fine, mesh ratio 2).

    Observed order p = log(|f1 - f2| / |f2 - f3|) / log(ratio); used when
    the differences have the same sign (monotone) and p lies in order_range,
    else the expected order. Returns a dict.
    """
    f1, f2, f3 = values[-3:]
    d1, d2 = f2 - f1, f3 - f2
    out = {"order_observed": None, "order_used": None, "note": None}
    if d1 == 0.0 or d2 == 0.0:
        out.update(extrapolated=f3, error_estimate=abs(d2), note="converged to round-off")
        return out
    p_obs = None
    if d1 * d2 > 0:
        p_obs = math.log(abs(d1) / abs(d2)) / math.log(ratio)
        out["order_observed"] = p_obs
    if p_obs is not None and order_range[0] <= p_obs <= order_range[1]:
        p = p_obs
    else:
        p = expected_order
        out["note"] = ("non-monotone" if p_obs is None else
                       f"observed order {p_obs:.3g} outside {list(order_range)}") + \
            f": expected order {p} used"
    out["order_used"] = p
    ext = f3 + d2 / (ratio ** p - 1.0)
    out["extrapolated"] = ext
    # error estimate of the extrapolated value: its distance from the finest
    # mesh (conservative: the extrapolation's own error is usually smaller)
    out["error_estimate"] = abs(ext - f3)
    return out


def order_of(values):
    if len(values) < 3:
        return None
    f1, f2, f3 = values[-3:]
    d1, d2 = f2 - f1, f3 - f2
    if d1 * d2 <= 0:
        return None
    return math.log(abs(d1) / abs(d2)) / math.log(2.0)


def describe():
    try:
        return subprocess.run(["git", "describe", "--always", "--dirty"], cwd=ROOT,
                              capture_output=True, text=True, check=True).stdout.strip()
    except Exception:
        return None


def dealii_version():
    v = {"header": None, "package": None}
    try:
        with open("/usr/include/deal.II/base/config.h") as f:
            m = re.search(r'DEAL_II_PACKAGE_VERSION\s+"([^"]+)"', f.read())
            v["header"] = m.group(1) if m else None
    except OSError:
        pass
    try:
        v["package"] = subprocess.run(
            ["dpkg-query", "-W", "-f=${Package} ${Version}", "libdeal.ii-dev"],
            capture_output=True, text=True, check=True).stdout.strip()
    except Exception:
        pass
    return v


class Runner:
    def __init__(self, exe, runs_dir, reuse, nice):
        self.exe, self.runs_dir, self.reuse, self.nice = exe, runs_dir, reuse, nice
        os.makedirs(runs_dir, exist_ok=True)
        self.total_seconds = 0.0

    def command(self, args):
        # as recorded in the JSON: relative to the repository root
        return " ".join(["build-reference/locking_reference"] + args)

    def run(self, args, allow_fail=False):
        key = "_".join(a.lstrip("-") for a in args).replace("/", "_")
        cache = os.path.join(self.runs_dir, key + ".json")
        if self.reuse and os.path.exists(cache):
            with open(cache) as f:
                d = json.load(f)
            self.total_seconds += d["_wall_seconds"]
            return d
        cmd = (["nice", "-n", str(self.nice)] if self.nice else []) + [self.exe] + args
        print("+", " ".join(cmd), file=sys.stderr, flush=True)
        t0 = time.time()
        p = subprocess.run(cmd, capture_output=True, text=True)
        dt = time.time() - t0
        self.total_seconds += dt
        if p.returncode != 0 and not allow_fail:
            sys.stderr.write(p.stderr)
            raise SystemExit(f"failed ({p.returncode}): {' '.join(cmd)}")
        d = json.loads(p.stdout.strip().splitlines()[-1])
        d["_wall_seconds"] = dt
        d["_returncode"] = p.returncode
        with open(cache, "w") as f:
            json.dump(d, f, sort_keys=True)
        print(f"  {dt:.1f} s", file=sys.stderr, flush=True)
        return d


def check_solve(d, what, max_residual=1e-8):
    s = d["solver"]
    if not s["converged"]:
        raise SystemExit(f"{what}: iterative solver did not converge")
    if s["relative_residual"] > max_residual:
        raise SystemExit(f"{what}: relative residual {s['relative_residual']}")


def series(runs, meshes, expected_order, quantities):
    """quantities: name -> function(run dict) -> float."""
    out = {"meshes": meshes,
           "n_dofs": [d["n_dofs"] for d in runs],
           "solver": [d["solver"]["method"] for d in runs],
           "iterations": [d["solver"]["iterations"] for d in runs],
           "relative_residual": [float(f"{d['solver']['relative_residual']:.2e}") for d in runs],
           "half_symmetric": [bool(d.get("half_symmetric", False)) for d in runs],
           "seconds": [round(d["_wall_seconds"], 1) for d in runs],
           "quantities": {}}
    for name, get in quantities.items():
        vals = [get(d) for d in runs]
        q = {"values": [r(v) for v in vals]}
        if len(vals) >= 3:
            rich = richardson(vals, expected_order=expected_order)
            q["extrapolated"] = r(rich["extrapolated"])
            q["error_estimate"] = float(f"{rich['error_estimate']:.3e}")
            q["order_observed"] = (None if rich["order_observed"] is None
                                   else round(rich["order_observed"], 3))
            q["order_used"] = (None if rich["order_used"] is None
                               else round(rich["order_used"], 3))
            if rich["note"]:
                q["note"] = rich["note"]
            # the same with order 1 (about the rate of the singularities at
            # the clamped edges, where the observed orders drift to)
            q["extrapolated_order_1"] = r(2.0 * vals[-1] - vals[-2])
            if len(vals) >= 4:
                o = order_of(vals[:-1])
                q["order_observed_coarser"] = None if o is None else round(o, 3)
        out["quantities"][name] = q
    return out


def box_quantities(runs):
    q = {"tip_uz": lambda d: d["points"]["tip"]["u"][2],
         "compliance": lambda d: d["compliance"]}
    for name in sorted(runs[0]["points"]):
        if name == "tip":
            continue
        q[name + "_uz"] = (lambda nm: lambda d: d["points"][nm]["u"][2])(name)
    # u_x only off the mid-plane z = 0.01: on it u_x (and everywhere u_y on
    # y = 0.01) is zero by symmetry, round-off only (~1e-19 m).
    for name in sorted(runs[0]["points"]):
        if abs(runs[0]["points"][name]["x"][2] - 0.01) > 1e-12:
            q[name + "_ux"] = (lambda nm: lambda d: d["points"][nm]["u"][0])(name)
    return q


def main():
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--build-dir", default=os.path.join(ROOT, "build-reference"))
    ap.add_argument("--out", default=os.path.join(ROOT, "test", "data",
                                                  "locking_reference.json"))
    ap.add_argument("--reuse", action="store_true")
    ap.add_argument("--nice", type=int, default=10)
    a = ap.parse_args()

    exe = os.path.join(a.build_dir, "locking_reference")
    if not os.path.exists(exe):
        raise SystemExit(f"{exe} not found: build tools/reference first (README.md)")
    R = Runner(exe, os.path.join(a.build_dir, "runs"), a.reuse, a.nice)
    t_start = time.time()

    # -- verification
    v = R.run(["verify"], allow_fail=True)["verification"]
    verification = {
        "all_pass": v["all_pass"],
        "exact": [{"case": c["case"], "pass": c["pass"],
                   "rel_nodal_error_u": float(f"{c['rel_nodal_error_u']:.2e}"),
                   "rel_nodal_error_p": float(f"{c['rel_nodal_error_p']:.2e}")}
                  for c in v["exact"]],
        "smooth_convergence": [{"nu": c["nu"], "formulation": c["formulation"],
                                "meshes": c["meshes"],
                                "l2_errors": [float(f"{e:.4e}") for e in c["l2_errors"]],
                                "rate_16_32": round(c["rate_16_32"], 3),
                                "pass": c["pass"]}
                               for c in v["smooth_convergence"]],
        "command": R.command(["verify"]),
    }
    if not v["all_pass"]:
        raise SystemExit("verification failed: no reference values written")

    commands = []
    benchmarks = {}

    # -- phantom box, mixed Q2-Q1
    box = {}
    for nu in NUS_BOX:
        runs = []
        for n in BOX_MESHES:
            args = box_args(nu, n, "mixed")
            d = R.run(args)
            check_solve(d, " ".join(args))
            commands.append(R.command(args))
            runs.append(d)
        box[repr(nu)] = series(runs, BOX_MESHES, 2.0, box_quantities(runs))
        box[repr(nu)]["energy_identity_max"] = float(
            f"{max(abs(d['energy_identity']) for d in runs):.1e}")
    benchmarks["phantom_box_mixed_Q2Q1"] = {
        "description": "box [0,0.04]x[0,0.02]x[0,0.02] m, n x n/2 x n/2 hexahedra, "
                       "E=1e7 Pa, rho=1000 kg/m^3, g=9.81 m/s^2 along -z, clamped "
                       "(u=0) at x=0.04, all other faces traction-free; Taylor-Hood "
                       "Q2-Q1 (p = lambda div u). Points: tip=(0,0.01,0.01), "
                       "pK=(0.0025K,0.01,0.01), p1A..p1E=(0.0025,0.01,0.01+0.0015j), "
                       "top_edge=(0,0.01,0.02); u in m; compliance = int f.u dV in J.",
        "extrapolated_from": "the three finest meshes",
        "by_nu": box,
    }

    # -- phantom box, displacement Q2 cross-check
    disp = {}
    for nu, meshes in DISP_MESHES.items():
        runs = []
        for n in meshes:
            args = box_args(nu, n, "displacement")
            d = R.run(args)
            # displacement Q2 at nu = 0.4999 is ill-conditioned (lambda/mu =
            # 5000): CG's recursive residual reaches 1e-12 while the true one
            # stalls near 1e-7 (UMFPACK: 4e-9 at n = 16, where the two tip
            # values agree to 1e-10). A cross-check, not a reference value.
            check_solve(d, " ".join(args), 1e-8 if nu < 0.49 else 1e-6)
            commands.append(R.command(args))
            runs.append(d)
        qs = {"tip_uz": lambda d: d["points"]["tip"]["u"][2],
              "compliance": lambda d: d["compliance"]}
        s = series(runs, meshes, 2.0, qs)
        mixed = box[repr(nu)]["quantities"]
        s["tip_uz_relative_to_mixed_extrapolated"] = [
            r(x / mixed["tip_uz"]["extrapolated"], 6) for x in s["quantities"]["tip_uz"]["values"]]
        disp[repr(nu)] = s
    benchmarks["phantom_box_displacement_Q2"] = {
        "description": "cross-check: the same box with plain (displacement-only) Q2",
        "by_nu": disp,
    }

    # -- Cook's membrane, plane strain, mixed Q2-Q1
    cook = {}
    for nu in NUS_COOK:
        runs = []
        for n in COOK_MESHES:
            args = ["cook", "--nu", repr(nu), "--n", str(n), "--E", "250", "--F", "100",
                    "--formulation", "mixed", "--solver", "direct"]
            d = R.run(args)
            check_solve(d, " ".join(args))
            commands.append(R.command(args))
            runs.append(d)
        qs = {"corner_uy": lambda d: d["points"]["corner"]["u"][1],
              "corner_ux": lambda d: d["points"]["corner"]["u"][0],
              "mid_uy": lambda d: d["points"]["mid"]["u"][1],
              "compliance": lambda d: d["compliance"]}
        cook[repr(nu)] = series(runs, COOK_MESHES, 2.0, qs)
    benchmarks["cook_membrane_plane_strain_mixed_Q2Q1"] = {
        "description": "Cook's membrane (0,0),(48,44),(48,60),(0,44), n x n "
                       "bilinearly mapped quadrilaterals, plane strain, E=250, clamped "
                       "at x=0, uniform shear traction F/16 (F=100) along +y on x=48; "
                       "corner=(48,60), mid=(48,52)",
        "extrapolated_from": "the three finest meshes",
        "by_nu": cook,
    }

    src = os.path.join(HERE, "locking_reference.cc")
    with open(src, "rb") as f:
        src_sha = hashlib.sha256(f.read()).hexdigest()
    doc = {
        "issue": 37,
        "generator": "tools/reference/make_reference.py",
        "tool": "tools/reference/locking_reference.cc",
        "tool_sha256": src_sha,
        "dealii": dealii_version(),
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d"),
        "commit": describe(),
        "richardson": "mesh ratio 2; observed order p = log2(|f1-f2|/|f2-f3|) from "
                      "the three finest meshes, used when the differences are "
                      "monotone and 0.5 <= p <= 6, else order_used = 2; "
                      "extrapolated = f3 + (f3-f2)/(2^p-1); error_estimate = "
                      "|extrapolated - f3|. extrapolated_order_1: the same with p = 1. "
                      "order_observed_coarser: the same from "
                      "the three meshes below the finest.",
        "verification": verification,
        "benchmarks": benchmarks,
        "commands": commands,
        # wall time of all runs (verify included) as they were made, reused or not
        "seconds_all_runs": round(R.total_seconds),
    }
    os.makedirs(os.path.dirname(a.out), exist_ok=True)
    with open(a.out, "w") as f:
        json.dump(doc, f, sort_keys=True, indent=1)
        f.write("\n")
    print(f"wrote {a.out} ({time.time() - t_start:.0f} s)", file=sys.stderr)

    # summary tables (Markdown, as in README.md)
    def table(results, nus, quantity, meshes, label, fmt, digits):
        print(f"| nu | {label}, n = " + ", ".join(str(n) for n in meshes) +
              " | extrapolated | error estimate | observed order (coarser) |")
        print("|---|---|---|---|---|")
        for nu in nus:
            q = results[repr(nu)]["quantities"][quantity]
            print(f"| {nu} | " + ", ".join(format(v, fmt) for v in q["values"]) +
                  f" | {q['extrapolated']:.{digits}} | {q['error_estimate']:.1e} | "
                  f"{q['order_observed']} ({q.get('order_observed_coarser')}) |")
        print()

    table(box, NUS_BOX, "tip_uz", BOX_MESHES, "tip u_z [m]", ".6e", "7e")
    table(cook, NUS_COOK, "corner_uy", COOK_MESHES, "corner u_y", ".6f", "5f")
    print("| nu | displacement-Q2 tip u_z, n = ... [m] | / mixed extrapolated |")
    print("|---|---|---|")
    for nu, meshes in DISP_MESHES.items():
        s = disp[repr(nu)]
        print(f"| {nu} | " + ", ".join(f"{n}: {v:.6e}" for n, v in
                                       zip(meshes, s["quantities"]["tip_uz"]["values"])) +
              " | " + ", ".join(str(x) for x in s["tip_uz_relative_to_mixed_extrapolated"]) + " |")

if __name__ == "__main__":
    main()

"""The study's statistics from the rows of ensemble.csv (successful runs only):

  outputs      per output: count, mean, standard deviation, 5/50/95 % percentiles, min, max
  target       the final target position's mean and covariance [m, m^2]
  sensitivity  per varied numeric key and output: Spearman's rank correlation (scipy) and its
               p-value; with --sampling saltelli also the first-order and total Sobol indices
               (Saltelli et al. 2010, Table 2: S_i = mean(f_B (f_ABi - f_A)) / V,
               ST_i = mean((f_A - f_ABi)^2) / (2 V), V the variance of f over A and B),
               over the sample indices whose runs in A, B and every AB_i succeeded
  statuses     runs per status

With several trajectories the same per trajectory (`by_trajectory`), and the sensitivities
only there: over mixed trajectories they would measure the trajectories, not the keys.
"""
import math

import numpy as np
from scipy import stats


def _num(x):
    try:
        v = float(x)
    except (TypeError, ValueError):
        return math.nan
    return v


def describe(values):
    v = np.array([x for x in values if math.isfinite(x)])
    if v.size == 0:
        return {"count": 0}
    p5, p50, p95 = np.percentile(v, [5, 50, 95])
    return {"count": int(v.size), "mean": float(v.mean()), "std": float(v.std(ddof=1)) if v.size > 1 else 0.0,
            "p5": float(p5), "p50": float(p50), "p95": float(p95), "min": float(v.min()), "max": float(v.max())}


def _target(rows):
    pts = np.array([[_num(r.get(f"target_{a}")) for a in "xyz"] for r in rows]) if rows else np.zeros((0, 3))
    pts = pts[np.all(np.isfinite(pts), axis=1)] if pts.size else pts
    if len(pts) < 2:
        return None
    return {"count": int(len(pts)), "mean": pts.mean(axis=0).tolist(), "covariance": np.cov(pts.T).tolist()}


def _spearman(rows, keys, outputs):
    out = {}
    for k in keys:
        x = np.array([_num(r[k]) for r in rows])
        out[k] = {}
        for o in outputs:
            y = np.array([_num(r.get(o)) for r in rows])
            ok = np.isfinite(x) & np.isfinite(y)
            if ok.sum() < 3 or np.ptp(x[ok]) == 0 or np.ptp(y[ok]) == 0:
                out[k][o] = {"spearman": None, "p_value": None, "count": int(ok.sum())}
                continue
            rho, p = stats.spearmanr(x[ok], y[ok])
            out[k][o] = {"spearman": float(rho), "p_value": float(p), "count": int(ok.sum())}
    return out


def _sobol(rows, keys, outputs):
    """First-order and total indices from the Saltelli blocks (rows with block A, B, AB:key)."""
    by = {}
    for r in rows:
        by.setdefault(r["block"], {})[int(r["sample"])] = r
    if "A" not in by or "B" not in by:
        return None
    out = {}
    for o in outputs:
        common = set(by["A"]) & set(by["B"])
        for k in keys:
            common &= set(by.get(f"AB:{k}", {}))
        idx = sorted(i for i in common if all(
            math.isfinite(_num(by[b][i].get(o))) for b in ["A", "B"] + [f"AB:{k}" for k in keys]))
        if len(idx) < 2:
            continue
        fa = np.array([_num(by["A"][i][o]) for i in idx])
        fb = np.array([_num(by["B"][i][o]) for i in idx])
        var = np.var(np.concatenate([fa, fb]))
        for k in keys:
            fab = np.array([_num(by[f"AB:{k}"][i][o]) for i in idx])
            first = float(np.mean(fb * (fab - fa)) / var) if var > 0 else None
            total = float(np.mean((fa - fab) ** 2) / (2 * var)) if var > 0 else None
            out.setdefault(k, {})[o] = {"first_order": first, "total": total, "count": len(idx)}
    return out


def _group(rows, keys, numeric_keys, outputs, saltelli):
    ok = [r for r in rows if r["status"] == "ok"]
    statuses = {}
    for r in rows:
        statuses[r["status"]] = statuses.get(r["status"], 0) + 1
    g = {"runs": len(rows), "statuses": statuses,
         "outputs": {o: describe([_num(r.get(o)) for r in ok]) for o in outputs},
         "target_final_position": _target(ok)}
    if numeric_keys:
        g["sensitivity"] = {"spearman": _spearman(ok, numeric_keys, outputs)}
        if saltelli:
            g["sensitivity"]["sobol"] = _sobol(ok, numeric_keys, outputs)
    return g


def summarize(rows, keys, numeric_keys, outputs, trajectories, saltelli):
    """rows: dicts of strings (ensemble.csv). Returns the statistics part of summary.json."""
    several = len(trajectories) > 1
    s = _group(rows, keys, [] if several else numeric_keys, outputs, saltelli)
    if several:
        s["by_trajectory"] = {t: _group([r for r in rows if r["trajectory"] == t], keys, numeric_keys, outputs, saltelli)
                              for t in trajectories}
    return s

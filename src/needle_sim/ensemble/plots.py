"""The study's figures (matplotlib, written in DIR):

  histograms.png        each output over the successful runs, its 5/50/95 % percentiles marked
  outputs_vs_keys.png   each output against each varied numeric key (one panel per pair),
                        Spearman's rho in the corner
  target_ellipse.png    the final target positions and their 95 % ellipse (covariance, chi^2
                        with 2 degrees of freedom) in the two planes that matter to a needle:
                        across the needle's axis (the lateral miss) and along it (the depth
                        miss in the plane of the largest lateral spread)
  by_trajectory.png     with several trajectories: each output per trajectory (points and medians)

Lengths are drawn in mm, forces in mN.
"""
import math

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from scipy import stats  # noqa: E402

from .statistics import _num  # noqa: E402


def _unit(output):
    if output.startswith("force"):
        return 1e3, "mN"
    if output.startswith(("target_", "tip_distance", "error_bound")):
        return 1e3, "mm"
    return 1.0, ""


def _label(output):
    scale, unit = _unit(output)
    return f"{output} [{unit}]" if unit else output


def _values(rows, key):
    return np.array([_num(r.get(key)) for r in rows])


def histograms(path, rows, outputs):
    n = len(outputs)
    cols = min(3, n)
    fig, axes = plt.subplots(math.ceil(n / cols), cols, figsize=(4.2 * cols, 3.2 * math.ceil(n / cols)), squeeze=False)
    for ax, o in zip(axes.flat, outputs):
        scale, _ = _unit(o)
        v = _values(rows, o) * scale
        v = v[np.isfinite(v)]
        if v.size:
            ax.hist(v, bins=max(5, min(40, int(math.sqrt(v.size)) * 2)), color="tab:blue", alpha=0.8)
            for q in np.percentile(v, [5, 50, 95]):
                ax.axvline(q, color="k", lw=0.8, ls="--")
        ax.set_xlabel(_label(o))
        ax.set_ylabel("runs")
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def outputs_vs_keys(path, rows, keys, outputs):
    fig, axes = plt.subplots(len(outputs), len(keys), figsize=(3.4 * len(keys), 2.6 * len(outputs)), squeeze=False)
    for i, o in enumerate(outputs):
        scale, _ = _unit(o)
        y = _values(rows, o) * scale
        for j, k in enumerate(keys):
            ax = axes[i][j]
            x = _values(rows, k)
            ok = np.isfinite(x) & np.isfinite(y)
            ax.scatter(x[ok], y[ok], s=10, color="tab:blue", alpha=0.8)
            if ok.sum() >= 3 and np.ptp(x[ok]) > 0 and np.ptp(y[ok]) > 0:
                rho = stats.spearmanr(x[ok], y[ok])[0]
                ax.text(0.03, 0.92, f"rho = {rho:.2f}", transform=ax.transAxes, fontsize=8)
            if i == len(outputs) - 1:
                ax.set_xlabel(k, fontsize=8)
            if j == 0:
                ax.set_ylabel(_label(o), fontsize=8)
            ax.tick_params(labelsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _ellipse(ax, mean2, cov2, color):
    vals, vecs = np.linalg.eigh(cov2)
    r = math.sqrt(stats.chi2.ppf(0.95, 2))
    t = np.linspace(0, 2 * math.pi, 100)
    pts = vecs @ (np.sqrt(np.maximum(vals, 0))[:, None] * r * np.array([np.cos(t), np.sin(t)]))
    ax.plot(mean2[0] + pts[0], mean2[1] + pts[1], color=color, lw=1.5, label="95 % ellipse")


def target_ellipse(path, rows, axis, target_name, planned=None):
    """axis: the needle's axis (unit vector, base -> tip). Positions in the frame (e1, e2, axis),
    e1 the direction of the largest lateral spread, relative to their mean [mm]."""
    pts = np.array([[_num(r.get(f"target_{a}")) for a in "xyz"] for r in rows])
    pts = pts[np.all(np.isfinite(pts), axis=1)] if pts.size else pts
    if len(pts) < 3:
        return False
    a = np.asarray(axis, dtype=float)
    a /= np.linalg.norm(a)
    helper = np.array([1.0, 0, 0]) if abs(a[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(a, helper)
    u /= np.linalg.norm(u)
    v = np.cross(a, u)
    lateral = np.cov(np.stack([pts @ u, pts @ v]))
    w = np.linalg.eigh(lateral)[1][:, -1]
    e1 = w[0] * u + w[1] * v
    e2 = np.cross(a, e1)
    frame = np.stack([e1, e2, a])  # rows
    mean = pts.mean(axis=0)
    q = (pts - mean) @ frame.T * 1e3
    cov = np.cov(q.T)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.6))
    for ax, (i, j), title in ((axes[0], (0, 1), "across the needle axis"), (axes[1], (0, 2), "along the needle axis")):
        ax.scatter(q[:, i], q[:, j], s=10, color="tab:blue", alpha=0.8, label="final position")
        _ellipse(ax, (0.0, 0.0), cov[np.ix_([i, j], [i, j])], "tab:red")
        names = ["e1 (largest lateral spread)", "e2", "needle axis (+: deeper)"]
        ax.set_xlabel(f"{names[i]} [mm]")
        ax.set_ylabel(f"{names[j]} [mm]")
        ax.set_title(f"{target_name}: {title}", fontsize=10)
        ax.axis("equal")
        ax.legend(fontsize=7)
    # The planned (rest) position is stated, not drawn: after a brain shift it lies millimetres
    # away and would shrink the spread to a dot.
    shift = "" if planned is None else f", mean - planned ({', '.join(f'{c:.3f}' for c in (mean - np.asarray(planned)) * 1e3)}) mm"
    fig.text(0.01, 0.01, f"positions relative to their mean ({', '.join(f'{c * 1e3:.2f}' for c in mean)}) mm{shift}; "
             f"e1 = ({', '.join(f'{c:.3f}' for c in e1)}), axis = ({', '.join(f'{c:.3f}' for c in a)})", fontsize=7)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def by_trajectory(path, rows, trajectories, outputs):
    fig, axes = plt.subplots(len(outputs), 1, figsize=(max(6, 0.8 * len(trajectories) + 2), 2.4 * len(outputs)), squeeze=False)
    for ax, o in zip(axes[:, 0], outputs):
        scale, _ = _unit(o)
        for i, t in enumerate(trajectories):
            y = _values([r for r in rows if r["trajectory"] == t], o) * scale
            y = y[np.isfinite(y)]
            ax.scatter(np.full(y.size, i), y, s=10, color="tab:blue", alpha=0.6)
            if y.size:
                ax.plot([i - 0.3, i + 0.3], [np.median(y)] * 2, color="k", lw=1.5)
        ax.set_xticks(range(len(trajectories)))
        ax.set_xticklabels(trajectories, rotation=30, fontsize=7, ha="right")
        ax.set_ylabel(_label(o), fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_all(out_dir, rows, keys, outputs, trajectories, axis, target_name, planned):
    """Every figure that the rows allow; returns the files written."""
    import os

    ok = [r for r in rows if r["status"] == "ok"]
    written = []
    if not ok:
        return written
    headline = [o for o in outputs if not o.startswith("target_") or o in ("target_u_final", "target_u_max", "target_motion_final")]
    histograms(os.path.join(out_dir, "histograms.png"), ok, headline)
    written.append("histograms.png")
    if keys:
        outputs_vs_keys(os.path.join(out_dir, "outputs_vs_keys.png"), ok, keys, headline)
        written.append("outputs_vs_keys.png")
    if axis is not None and target_name and target_ellipse(os.path.join(out_dir, "target_ellipse.png"), ok, axis, target_name, planned):
        written.append("target_ellipse.png")
    if len(trajectories) > 1:
        by_trajectory(os.path.join(out_dir, "by_trajectory.png"), rows, trajectories, headline)
        written.append("by_trajectory.png")
    return written

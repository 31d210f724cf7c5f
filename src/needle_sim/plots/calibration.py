"""Plot of a calibration (needle_sim calibrate): DIR/fit.png from DIR/fit.csv, the measured,
start and fitted axial force on the holder against time and against the base's advance (the
sign of every report: a force sensor's reading, negative when the tissue resists).

    scripts/plot_calibration.py results/calibration
"""
import csv
import json
import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from ..run_outputs import axial_force_label


def main():
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    d = sys.argv[1]
    with open(os.path.join(d, "fit.csv"), newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        sys.exit(f"plot_calibration: {d}/fit.csv has no rows")
    col = {k: [float(r[k]) for r in rows] for k in rows[0]}
    title = ""
    try:
        with open(os.path.join(d, "calibration.json")) as f:
            j = json.load(f)
        title = ", ".join(f"{k.split('.')[-1]} = {v['value']:.4g}" for k, v in j["parameters"].items())
        title += f"; rms {j['rms_residual_n'] * 1e3:.3g} mN"
    except (OSError, KeyError, ValueError):
        pass
    fig, ax = plt.subplots(1, 2, figsize=(12, 4.5))
    for a, x, label in ((ax[0], col["t"], "time [s]"), (ax[1], [v * 1e3 for v in col["advance"]], "base advance [mm]")):
        a.plot(x, [v * 1e3 for v in col["measured"]], ".", ms=2, color="0.5", label="measured")
        a.plot(x, [v * 1e3 for v in col["start"]], "--", color="tab:blue", label="start values")
        a.plot(x, [v * 1e3 for v in col["fitted"]], "-", color="tab:red", label="fitted")
        a.set_xlabel(label)
        a.set_ylabel(axial_force_label("mN"), fontsize=8)
        a.grid(alpha=0.3)
        a.legend()
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    out = os.path.join(d, "fit.png")
    fig.savefig(out, dpi=110)
    print(f"plot_calibration: wrote {out}")


if __name__ == "__main__":
    main()

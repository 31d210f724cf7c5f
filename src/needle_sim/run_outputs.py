"""What the plots and studies read of a `needle_sim run` folder (doc/cli.md): its summary.json
with the names of the needles, probes and targets in scene order (summary.json "names"), and
its time series. They read what the tool wrote and recompute no physics: the axial force on a
needle's holder is the column <needle>_axial_force, with the one sign of every report
(doc/method.md "Observables"): the needle's force on its holder along the needle, what a force
sensor between them reads, negative when the tissue resists the insertion."""
import csv
import json
import os

# The one wording of the axial force on a plot's axis.
AXIAL_FORCE_LABEL = "axial force on the holder [{unit}]\n(a force sensor's reading: − when the tissue resists)"


def axial_force_label(unit="mN"):
    return AXIAL_FORCE_LABEL.format(unit=unit)


def load_summary(run_dir):
    with open(os.path.join(run_dir, "summary.json")) as f:
        return json.load(f)


def load_rows(run_dir):
    with open(os.path.join(run_dir, "timeseries.csv"), newline="") as f:
        return list(csv.DictReader(f))


def names(summary, kind):
    """kind: "needles", "probes" or "targets": the run's names in scene order."""
    if "names" not in summary:
        raise KeyError("summary.json has no 'names' (a run of an older needle_sim: run it again)")
    return summary["names"][kind]

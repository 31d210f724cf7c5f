"""The study's folder, written so that an interruption at any moment loses at most the runs
in flight:

  study.json     the definition (scene, keys and distributions, sampling, seed, trajectories,
                 overrides, output columns): written once, before any run; --resume reads it
  samples.csv    the planned table: run id, block, sample, trajectory, the values
  ensemble.csv   one row per finished run, appended (and flushed to disk) as each arrives;
                 every record is one line, so a line cut by a kill is recognised and dropped
  summary.json   the statistics, replaced atomically (written beside, then renamed)
"""
import csv
import json
import os

from .distributions import UsageError
from .run_task import RUN_STATUSES

LEAD = ["run", "block", "sample", "trajectory"]
TAIL = ["status", "exit_code", "message"]
TIMES = ["wall_time_s", "task_s", "worker"]


def columns(keys, outputs):
    return LEAD + list(keys) + TAIL + list(outputs) + TIMES


def write_json_atomic(path, data):
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(data, f, indent=2, sort_keys=False)
        f.write("\n")
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def write_csv_atomic(path, header, rows):
    tmp = path + ".tmp"
    with open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=header, lineterminator="\n")
        w.writeheader()
        w.writerows(rows)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


class ResultLog:
    """ensemble.csv: existing complete rows on open, then one appended line per result."""

    def __init__(self, path, header):
        self.path, self.header = path, header
        self.rows = {}
        if os.path.exists(path):
            self._read()
        else:
            write_csv_atomic(path, header, [])

    def _read(self):
        with open(self.path, newline="") as f:
            text = f.read()
        lines = text.split("\n")
        if lines and lines[-1] != "":
            lines = lines[:-1]  # the last record was cut by an interruption: it did not happen
        reader = csv.DictReader(lines)
        if reader.fieldnames != self.header:
            raise UsageError(f"{self.path}: its columns differ from the study's (another study in this folder?)")
        rows = [r for r in reader if None not in r and r.get("status") in RUN_STATUSES]
        # Rows of runs that were lost (the engine gave up on them) are dropped: --resume runs them again.
        self.rows = {int(r["run"]): r for r in rows}
        write_csv_atomic(self.path, self.header, [self.rows[k] for k in sorted(self.rows)])

    def append(self, row):
        flat = {k: ("" if row.get(k) is None else row.get(k)) for k in self.header}
        flat["message"] = " ".join(str(flat["message"]).split())  # one line per record
        for k, v in flat.items():
            if isinstance(v, float):
                flat[k] = repr(v)  # round-trips: the row's numbers are the run's, bit for bit
        with open(self.path, "a", newline="") as f:
            csv.DictWriter(f, fieldnames=self.header, lineterminator="\n").writerow(flat)
            f.flush()
            os.fsync(f.fileno())
        self.rows[int(flat["run"])] = {k: str(v) for k, v in flat.items()}

"""The Dask task: one `needle_sim run` in a private folder, reduced to the numbers of a row.

Runs on a worker (shipped by value with cloudpickle: a worker needs Python with
dask.distributed and the needle_sim tool, not this package). Each attempt gets a folder of
its own: a worker killed mid-run leaves its attempt's folder behind, and the retry on
another worker cannot mix its files with it. The tool is started so that it dies with the
worker (PR_SET_PDEATHSIG): a killed worker leaves no orphan run burning a core.

Statuses: `ok`, `numerical_failure` (exit 3: summary.json says so, with a message),
`invalid_input` (exit 2: the tool's message), `crashed` (any other exit, a signal or the
--timeout: the end of its stderr); `lost` (the tool could not be started on the worker:
--resume runs it again). The outputs (SI units):

  target_u_final, target_u_max   the target's displacement from its rest (planning) position,
                                 at the end and its largest over the run [m] (brain shift included)
  target_motion_final            its motion since the first step (after the brain shift) [m]
  target_x, target_y, target_z   its final position [m]
  error_bound                    the goal-oriented bound on target_u (run option --target-error)
  tip_distance_<needle>          the needle's tip to the target at the end [m]
  tip_distance_min_<needle>      ... its smallest over the run [m]
  force_peak_<needle>            the largest force of the needle on its holder, |holder_f| [N]

The names (needles, targets) come from summary.json's "names", in scene order.
"""
import csv
import ctypes
import json
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time

RUN_STATUSES = ("ok", "numerical_failure", "invalid_input", "crashed")


def _die_with_parent():
    """A function for preexec_fn: prctl(PR_SET_PDEATHSIG, SIGKILL) in the child, so the run is
    killed when the thread that started it dies. That thread is the worker's task thread,
    which lives until the task returns (it waits for the run), so in effect: when the worker
    dies. prctl is looked up here, in the parent: the child only calls it (no dlopen between
    fork and exec). Linux only; elsewhere None (the run outlives a killed worker)."""
    try:
        prctl = ctypes.CDLL("libc.so.6", use_errno=True).prctl
    except (OSError, AttributeError):
        return None
    return lambda: prctl(1, signal.SIGKILL)


def _tail(text, lines=3):
    return " | ".join(line.strip() for line in text.strip().splitlines()[-lines:])


def _column_max(path, columns, combine):
    """The largest of combine(values of `columns`) over the rows of a CSV time series."""
    best = None
    with open(path, newline="") as f:
        reader = csv.reader(f)
        header = next(reader)
        idx = [header.index(c) for c in columns]
        for row in reader:
            v = combine([float(row[i]) for i in idx])
            best = v if best is None or v > best else best
    return best


def outputs(summary, timeseries, target):
    """The row's numbers from a finished run's summary.json (dict) and timeseries.csv (path);
    target None: the scene's first."""
    out = {}
    names = summary["names"]  # scene order (summary.json's objects sort their keys)
    target = target or (names["targets"][0] if names["targets"] else None)
    needles = names["needles"]
    for n in needles:
        out[f"force_peak_{n}"] = _column_max(timeseries, [f"{n}_holder_f{a}" for a in "xyz"],
                                             lambda v: (v[0] ** 2 + v[1] ** 2 + v[2] ** 2) ** 0.5)
    t = (summary.get("targets") or {}).get(target) if target else None
    if target and t is None:
        raise KeyError(f"the run has no target '{target}' (it has {', '.join(summary.get('targets') or {}) or 'none'})")
    if t is not None:
        out["target_u_final"] = t["displacement_norm"]
        out["target_u_max"] = _column_max(timeseries, [f"{target}_u"], lambda v: v[0])
        out["target_motion_final"] = t["motion_since_start"]
        out["target_x"], out["target_y"], out["target_z"] = t["position"]
        if t.get("error_bound") is not None:
            out["error_bound"] = t["error_bound"]
        for n in needles:
            out[f"tip_distance_{n}"] = t["tip_distance"][n]
            if n in t.get("tip_distance_min", {}):
                out[f"tip_distance_min_{n}"] = t["tip_distance_min"][n]
    # What the study needs to know of the scene once (the preflight): names, plan, axis.
    scene = {"target": target, "needles": needles,
             "planned": t["planned"] if t is not None else None,
             "axis": summary["needles"][needles[0]]["direction"] if needles else None}
    return out, scene


def run_sample(tool, scene, args, run_id, target, keep_dir=None, timeout=None):
    """Run `tool run scene --out PRIVATE --quiet args...`; return the row's fields as a dict.
    keep_dir: where the run's folder is moved when done (None: deleted)."""
    t0 = time.monotonic()
    parent = None
    if keep_dir:
        parent = os.path.dirname(keep_dir)
        os.makedirs(parent, exist_ok=True)
    private = tempfile.mkdtemp(prefix=f".run{run_id}.", dir=parent)
    # One BLAS thread while the scene loads too: the ensemble runs a sample per core.
    cmd = [tool, "--setup-threads", "1", "run", scene, "--out", private, "--quiet"] + list(args)
    result = {"worker": f"{socket.gethostname()}:{os.getpid()}"}
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, preexec_fn=_die_with_parent())
        code, stderr = p.returncode, p.stderr
    except subprocess.TimeoutExpired:
        code, stderr = None, f"timed out after {timeout} s"
    except OSError as e:  # the worker has no such tool: the engine's fault, not the sample's
        code, stderr = "lost", f"cannot start {tool} on {socket.gethostname()}: {e.strerror}"
    if code == "lost":
        result.update(status="lost", message=stderr, exit_code="", task_s=time.monotonic() - t0)
        shutil.rmtree(private, ignore_errors=True)
        return result
    result["exit_code"] = "" if code is None else code
    summary_path = os.path.join(private, "summary.json")
    summary = None
    if code in (0, 3) and os.path.exists(summary_path):
        with open(summary_path) as f:
            summary = json.load(f)
    if code == 0 and summary is not None:
        result["status"] = summary.get("status", "ok")
        result["message"] = ""
        result["wall_time_s"] = summary.get("wall_time_s")
        try:
            result["outputs"], result["scene"] = outputs(summary, os.path.join(private, "timeseries.csv"), target)
        except KeyError as e:
            result.update(status="invalid_input", message=str(e.args[0]))
    elif code == 3:
        result["status"] = "numerical_failure"
        result["message"] = (summary or {}).get("message") or _tail(stderr)
        if summary and summary.get("failed_step") is not None:
            result["message"] += f" (step {summary['failed_step']})"
        result["wall_time_s"] = (summary or {}).get("wall_time_s")
    elif code == 2:
        result["status"], result["message"] = "invalid_input", _tail(stderr)
    else:
        why = f"killed by signal {-code}" if isinstance(code, int) and code < 0 else f"exit status {code}"
        result["status"], result["message"] = "crashed", (f"{why}: " if code is not None else "") + _tail(stderr)
    result["task_s"] = time.monotonic() - t0
    if keep_dir:
        shutil.rmtree(keep_dir, ignore_errors=True)
        os.replace(private, keep_dir)
    else:
        shutil.rmtree(private, ignore_errors=True)
    return result

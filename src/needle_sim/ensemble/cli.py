"""needle_sim ensemble: the command line (reference: doc/ensemble.md).

    needle_sim ensemble SCENE --samples N --vary KEY=DIST ... [--sampling lhs|sobol|saltelli]
        [--seed S] [--trajectories FILE] [--set KEY=VALUE ...] [--target NAME]
        [--target-error] [--target-error-every N] [--scheduler tcp://HOST:PORT] [--workers K]
        [--connect-timeout S] [--timeout S] [--keep-runs] [--resume] [--no-plot] [--tool PATH] --out DIR

Exit status: 0 every planned run has a row (failed samples included); 1 runs were lost (the
engine gave up on them: --resume runs them again); 2 invalid input, before any run; 130
interrupted (--resume continues).
"""
import argparse
import json
import os
import secrets
import sys
import time

from .. import paths

from . import design as design_mod
from . import plots, statistics, store, trajectories
from .distributions import UsageError, format_value, parse_all
from .run_task import run_sample

# The study's definition: what --resume takes from study.json and checks against the command line.
DEFINITION = ("scene", "vary", "sampling", "samples", "seed", "set", "trajectories", "target", "run_args")
PREFLIGHT_DURATION = "time.duration=1e-9"  # one step: the scene is loaded, validated and built


def parser():
    ap = argparse.ArgumentParser(
        prog="needle_sim ensemble",
        description="Run a scene many times with sampled --set values (and base trajectories) on a Dask "
                    "cluster; collect the numbers, their statistics and plots (doc/ensemble.md).")
    ap.add_argument("scene", nargs="?", help="scene file, or a shipped scene's name (not with --resume)")
    ap.add_argument("--out", "-o", required=True, help="study folder: study.json, samples.csv, ensemble.csv, summary.json, plots")
    ap.add_argument("--samples", "-n", type=int, help="material samples (each run on every trajectory)")
    ap.add_argument("--vary", action="append", metavar="KEY=DIST",
                    help="a scene key and its distribution: normal(mu,sigma), lognormal(median,factor), "
                         "uniform(a,b), choice(v1,v2,...) (repeatable)")
    ap.add_argument("--sampling", choices=design_mod.METHODS, help="lhs (default), sobol, saltelli (Sobol indices; N (d+2) runs)")
    ap.add_argument("--seed", type=int, help="seed of the sampling (default: a random one, recorded in study.json)")
    ap.add_argument("--trajectories", help="YAML list of base trajectories (entry points), crossed with the samples")
    ap.add_argument("--set", action="append", metavar="KEY=VALUE", help="a fixed override for every run (repeatable)")
    ap.add_argument("--target", help="the target whose motion is reported (default: the scene's first)")
    ap.add_argument("--target-error", action="store_true", help="pass --target-error to the runs: the error_bound column")
    ap.add_argument("--target-error-every", type=int, metavar="N", help="... estimated every N steps")
    ap.add_argument("--scheduler", help="address of a running Dask scheduler (default: a LocalCluster)")
    ap.add_argument("--connect-timeout", type=float, default=10, metavar="S", help="give up connecting to --scheduler after S seconds")
    ap.add_argument("--workers", type=int, help="LocalCluster workers (default: one per core)")
    ap.add_argument("--timeout", type=float, help="a run taking longer is stopped and recorded as crashed [s]")
    ap.add_argument("--keep-runs", action="store_true", help="keep each run's folder as DIR/runs/NNNNN")
    ap.add_argument("--resume", action="store_true", help="continue the study in DIR: run only what is missing")
    ap.add_argument("--no-plot", action="store_true", help="no figures")
    ap.add_argument("--tool", default=paths.tool(), help="the needle_sim tool (default: %(default)s)")
    return ap


def resolve_scene(name):
    """(what the workers' tool is given, the local file): like the tool, a path that exists or
    has a '/' is used as given (made absolute); a bare name is a shipped scene, which each
    worker's tool finds in its own share folder."""
    if os.path.exists(name) or "/" in name:
        if not os.path.isfile(name):
            raise UsageError(f"scene {name}: no such file")
        return os.path.abspath(name), os.path.abspath(name)
    local = paths.scene(name)
    if not os.path.isfile(local):
        raise UsageError(f"scene {name}: no such file (nor in {os.path.dirname(local)})")
    return name, local


def resolve_trajectories(path):
    if os.path.exists(path) or "/" in path:
        return path
    shipped = os.path.join(paths.share_dir(), "config", "studies", path)
    return shipped if os.path.exists(shipped) else path


def new_definition(a):
    if not a.scene:
        raise UsageError("SCENE is required (unless --resume)")
    scene_arg, scene_file = resolve_scene(a.scene)
    vary = a.vary or []
    if vary and a.samples is None:
        raise UsageError("--samples N is required with --vary")
    run_args = (["--target-error"] if a.target_error or a.target_error_every else []) + (
        ["--target-error-every", str(a.target_error_every)] if a.target_error_every else [])
    traj = None
    if a.trajectories:
        path = resolve_trajectories(a.trajectories)
        traj = [t.to_json() for t in trajectories.load(path, a.tool, scene_file, a.set or [])]
    return {"scene": scene_arg, "scene_file": scene_file, "vary": vary, "sampling": a.sampling or "lhs",
            "samples": a.samples if a.samples is not None else 1,
            "seed": a.seed if a.seed is not None else secrets.randbits(32),
            "set": a.set or [], "trajectories": traj, "trajectories_file": a.trajectories,
            "target": a.target, "run_args": run_args}


def check_resume(a, study):
    """The command line may repeat the study's definition, not change it."""
    d = study["definition"]
    given = {"vary": a.vary, "sampling": a.sampling, "samples": a.samples, "seed": a.seed, "set": a.set,
             "target": a.target, "trajectories_file": a.trajectories}
    for k, v in given.items():
        if v is not None and v != d.get(k):
            raise UsageError(f"--resume: DIR's study has {k} = {d.get(k)!r}, the command line {v!r} "
                             "(a changed study needs another --out)")
    if a.scene and resolve_scene(a.scene)[0] != d["scene"]:
        raise UsageError(f"--resume: DIR's study runs {d['scene']}, not {a.scene}")


def plan(definition, design):
    """[(run id, block, sample, trajectory name, values as --set text, all --set arguments)]."""
    trajs = definition["trajectories"] or [{"name": "scene", "set": []}]
    runs = []
    for t in trajs:
        for i, (block, sample, _) in enumerate(design.rows):
            values = [v if d.name == "choice" else format_value(v) for d, v in zip(design.dists, design.values[i])]
            key_sets = [f"{d.key}={v}" for d, v in zip(design.dists, values)]
            sets = definition["set"] + t["set"] + key_sets
            runs.append((len(runs), block, sample, t["name"], values, sets))
    return runs


def _set_args(sets):
    return [x for s in sets for x in ("--set", s)]


def preflight(engine, tool, definition, design, runs):
    """One-step runs of the extreme configurations, on the cluster, before any sample: an
    invalid key, a value outside a key's valid range, a trajectory that starts inside the
    tissue are refused now (exit 2 with the tool's message). Returns the scene facts
    (target, needles, plan, axis) of the first that ran."""
    dists = design.dists
    corners = []
    if dists:
        cols = list(zip(*(r[4] for r in runs)))
        lo = [min(c, key=float) if d.numeric else c[0] for d, c in zip(dists, cols)]
        hi = [max(c, key=float) if d.numeric else c[-1] for d, c in zip(dists, cols)]
        corners = [("lowest values", lo), ("highest values", hi)]
        for j, d in enumerate(dists):  # every value of a choice, at least once
            if not d.numeric:
                corners += [(f"{d.key}={v}", [v if k == j else lo[k] for k in range(len(dists))]) for v in sorted(set(cols[j]))]
    trajs = definition["trajectories"] or [{"name": "scene", "set": []}]
    configs = []
    for ti, t in enumerate(trajs):
        for ci, (what, vals) in enumerate(corners or [("scene values", [])]):
            if ti > 0 and ci > 0:
                continue  # every trajectory once, every corner once
            sets = definition["set"] + t["set"] + [f"{d.key}={v}" for d, v in zip(dists, vals)] + [PREFLIGHT_DURATION]
            configs.append((f"trajectory '{t['name']}', {what}", sets))
    results = {}
    engine.map(run_sample, [(i, (tool, definition["scene"], _set_args(s) + definition["run_args"], f"pre{i}",
                                 definition["target"])) for i, (_, s) in enumerate(configs)],
               lambda i, r: results.__setitem__(i, r), label="preflight runs")
    facts = None
    for i, (what, sets) in enumerate(configs):
        r = results[i]
        if isinstance(r, Exception):
            raise UsageError(f"preflight ({what}): the engine failed: {r!r}")
        if r["status"] in ("invalid_input", "lost"):
            raise UsageError(f"preflight ({what}): {r['message']}\n  overrides: {' '.join(sets[:-1])}")
        if r["status"] != "ok":
            print(f"ensemble: warning: preflight ({what}): {r['status']}: {r['message']}", file=sys.stderr)
        elif facts is None:
            facts = dict(r["scene"], outputs=list(r["outputs"]))
    if facts is None:
        raise UsageError("preflight: no configuration of the scene ran its first step")
    return facts


def output_columns(facts, definition):
    cols = []
    if facts["target"]:
        cols += ["target_u_final", "target_u_max", "target_motion_final", "target_x", "target_y", "target_z"]
        if definition["run_args"]:
            cols.append("error_bound")
        for n in facts["needles"]:
            cols += [f"tip_distance_{n}", f"tip_distance_min_{n}"]
    cols += [f"force_peak_{n}" for n in facts["needles"]]
    return cols


def write_samples(path, keys, runs):
    rows = [dict(zip(store.LEAD + keys, [r[0], r[1], r[2], r[3]] + list(r[4]))) for r in runs]
    store.write_csv_atomic(path, store.LEAD + keys, rows)


class Study:
    """The running study: turns results into rows, keeps summary.json current."""

    def __init__(self, out, definition, facts, design, runs, log, engine_text, workers):
        self.out, self.definition, self.facts, self.design, self.runs, self.log = out, definition, facts, design, runs, log
        self.keys = [d.key for d in design.dists]
        self.numeric = [d.key for d in design.dists if d.numeric]
        self.outputs = facts["columns"]
        self.engine_text, self.workers = engine_text, workers
        self.t0 = time.monotonic()
        self.session_done = 0
        self.task_s, self.run_s = [], []  # this session's: the whole task, the tool's stepping
        self.last_summary = 0.0

    def on_result(self, run_id, result):
        rid, block, sample, traj, values, _ = self.runs[run_id]
        if isinstance(result, Exception):
            result = {"status": "lost", "message": f"{type(result).__name__}: {result}"}
        row = {"run": rid, "block": block, "sample": sample, "trajectory": traj, **dict(zip(self.keys, values))}
        row.update({k: result.get(k) for k in ("status", "exit_code", "message", "wall_time_s", "task_s", "worker")})
        row.update(result.get("outputs") or {})
        self.log.append(row)
        self.session_done += 1
        if result.get("task_s") is not None:
            self.task_s.append(result["task_s"])
        if result.get("wall_time_s") is not None:
            self.run_s.append(result["wall_time_s"])
        if time.monotonic() - self.last_summary > 2.0:
            self.write_summary()

    def throughput(self, elapsed):
        """This session's runs per second against the ideal, workers / mean task time: the
        share lost to the engine (scheduling, transfers, idle workers at the end)."""
        t = {"runs": self.session_done, "wall_s": elapsed, "workers": self.workers,
             "runs_per_s": self.session_done / elapsed if elapsed > 0 else None}
        if self.task_s:
            mean_task = sum(self.task_s) / len(self.task_s)
            t["mean_task_s"] = mean_task
            t["efficiency"] = t["runs_per_s"] * mean_task / self.workers if t["runs_per_s"] and self.workers else None
        if self.run_s and self.task_s:
            # the tool's time outside its steps (loading, meshing, brain shift) and the task's own
            t["mean_overhead_s"] = t["mean_task_s"] - sum(self.run_s) / len(self.run_s)
        return t

    def write_summary(self, final=False):
        rows = [self.log.rows[k] for k in sorted(self.log.rows)]
        trajs = [t["name"] for t in (self.definition["trajectories"] or [{"name": "scene"}])]
        el = time.monotonic() - self.t0
        s = {"scene": self.definition["scene"], "target": self.facts["target"],
             "varied": [d.to_json() for d in self.design.dists], "sampling": self.definition["sampling"],
             "seed": self.definition["seed"], "trajectories": trajs,
             "runs": {"planned": len(self.runs), "recorded": len(rows), "complete": len(rows) == len(self.runs) and final},
             "engine": self.engine_text,
             "session": self.throughput(el),
             "units": "SI: lengths m, forces N, times s",
             **statistics.summarize(rows, self.keys, self.numeric, self.outputs, trajs,
                                    self.definition["sampling"] == "saltelli")}
        store.write_json_atomic(os.path.join(self.out, "summary.json"), s)
        self.last_summary = time.monotonic()
        return rows, trajs


def run(a):
    out = os.path.abspath(a.out)
    study_path = os.path.join(out, "study.json")
    if a.resume:
        if not os.path.exists(study_path):
            raise UsageError(f"--resume: {out} holds no study (no study.json)")
        with open(study_path) as f:
            study = json.load(f)
        check_resume(a, study)
        definition, facts = study["definition"], study["facts"]
    else:
        if os.path.exists(study_path):
            raise UsageError(f"{out} already holds a study: --resume continues it; a new one needs another --out")
        definition, facts = new_definition(a), None
    if a.workers is not None and a.workers < 1:
        raise UsageError(f"--workers {a.workers}: must be at least 1")
    if not a.scheduler and not (os.path.isfile(a.tool) and os.access(a.tool, os.X_OK)):
        raise UsageError(f"--tool {a.tool}: no executable needle_sim tool there (build first: bash scripts/test.sh)")
    dists = parse_all(definition["vary"])
    design = design_mod.make_design(dists, definition["samples"], definition["sampling"], definition["seed"])
    runs = plan(definition, design)
    keys = [d.key for d in dists]

    from .engine import Engine  # imported late: a bad command line is refused without starting Dask

    def start_engine():
        e = Engine(a.scheduler, a.workers, a.connect_timeout)
        print(f"ensemble: {e.describe()}", file=sys.stderr)
        return e

    engine = None  # started only when there is something to run
    try:
        if facts is None:
            os.makedirs(out, exist_ok=True)
            engine = start_engine()
            facts = preflight(engine, a.tool, definition, design, runs)
            facts["columns"] = output_columns(facts, definition)
            write_samples(os.path.join(out, "samples.csv"), keys, runs)
            store.write_json_atomic(study_path, {"definition": definition, "facts": facts, "tool": a.tool,
                                                 "created": time.strftime("%Y-%m-%dT%H:%M:%S%z")})
            print(f"ensemble: {len(runs)} runs ({len(design)} samples x {len(runs) // len(design)} trajectories), "
                  f"seed {definition['seed']}, target {facts['target']}", file=sys.stderr)
        log = store.ResultLog(os.path.join(out, "ensemble.csv"), store.columns(keys, facts["columns"]))
        missing = [r for r in runs if r[0] not in log.rows]
        if a.resume:
            print(f"ensemble: resuming: {len(log.rows)} of {len(runs)} runs recorded, running the {len(missing)} missing",
                  file=sys.stderr)
        if missing and engine is None:
            engine = start_engine()
        study = Study(out, definition, facts, design, runs, log, engine.describe() if engine else None,
                      engine.threads() if engine else 0)
        keep = os.path.join(out, "runs") if a.keep_runs else None
        jobs = [(r[0], (a.tool, definition["scene"], _set_args(r[5]) + definition["run_args"], r[0], facts["target"],
                        os.path.join(keep, f"{r[0]:05d}") if keep else None, a.timeout)) for r in missing]
        if jobs:
            engine.map(run_sample, jobs, study.on_result)
    finally:
        if engine is not None:
            engine.close()
    rows, trajs = study.write_summary(final=True)
    if not a.no_plot:
        files = plots.write_all(out, rows, study.numeric, facts["columns"], trajs, facts.get("axis"),
                                facts["target"], facts.get("planned"))
        print(f"ensemble: plots: {', '.join(files) or 'none (no successful run)'}", file=sys.stderr)
    statuses = {}
    for r in rows:
        statuses[r["status"]] = statuses.get(r["status"], 0) + 1
    print(f"ensemble: {len(rows)}/{len(runs)} runs recorded ({', '.join(f'{v} {k}' for k, v in sorted(statuses.items()))}); "
          f"{out}/ensemble.csv, summary.json", file=sys.stderr)
    lost = statuses.get("lost", 0)
    if lost:
        print(f"ensemble: {lost} runs lost by the engine: --resume --out {out} runs them again", file=sys.stderr)
    return 1 if lost else 0


def main(argv=None):
    a = parser().parse_args(argv)  # argparse exits 2 on a bad command line
    try:
        return run(a)
    except UsageError as e:
        print(f"needle_sim ensemble: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"\nneedle_sim ensemble: interrupted; the rows so far are in {a.out}/ensemble.csv: "
              f"--resume --out {a.out} runs the rest", file=sys.stderr)
        return 130

"""The engine: a Dask cluster that runs the tasks, and the loop that collects their results.

Local: a dask.distributed LocalCluster of worker processes with one thread each (a run is
one single-threaded tool process), one per core by default. Remote: --scheduler connects to a
running scheduler (`dask scheduler` / `dask worker`, Debian's `dask-scheduler` /
`dask-worker`, or a cluster manager's); its workers need the tool and the scene at the paths
the study names (a shared file system, or the package installed alike on every machine).

Faults: a task whose worker dies is run again on another by the scheduler (it gives up after
`distributed.scheduler.allowed-failures` deaths, 3 by default: the row is then `lost`, and
--resume runs it again). Results are handed to `on_result` as they arrive, in any order.
"""
import logging
import math
import os
import sys
import time
import uuid

from .distributions import UsageError


class Engine:
    def __init__(self, scheduler=None, workers=None, connect_timeout=10):
        import cloudpickle
        from dask.distributed import Client, LocalCluster

        from . import run_task

        # Ship the task's code with each task: workers need Python with dask.distributed and
        # the needle_sim tool, not this package on their path. Dask pickles a function by value
        # only if its own module (not its package) is registered; run_task imports only the
        # standard library.
        cloudpickle.register_pickle_by_value(run_task)
        self.cluster = None
        if scheduler:
            try:
                self.client = Client(scheduler, timeout=f"{connect_timeout}s")
            except (OSError, TimeoutError) as e:
                raise UsageError(f"--scheduler {scheduler}: cannot connect: {e}")
            if not self.client.scheduler_info().get("workers"):
                print(f"ensemble: the scheduler at {scheduler} has no workers yet; waiting for one", file=sys.stderr)
                try:
                    self.client.wait_for_workers(1, timeout=60)
                except TimeoutError:
                    self.client.close()
                    raise UsageError(f"--scheduler {scheduler}: no worker joined within 60 s")
        else:
            n = workers or len(os.sched_getaffinity(0))
            self.cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                        dashboard_address=None, silence_logs=logging.ERROR)
            self.client = Client(self.cluster)

    def describe(self):
        w = self.client.scheduler_info().get("workers", {})
        kind = "LocalCluster" if self.cluster else "scheduler"
        return f"{kind} {self.client.scheduler.address}, {len(w)} workers, {self.threads()} threads"

    def threads(self):
        """Tasks the cluster runs at once (one per worker thread)."""
        w = self.client.scheduler_info().get("workers", {})
        return sum(x.get("nthreads", 1) for x in w.values()) or 1

    def map(self, fn, jobs, on_result, label="runs"):
        """jobs: [(job id, args tuple)]. Calls on_result(job id, result or exception) as each
        finishes; shows progress with an ETA on stderr. Returns when all are done."""
        from dask.distributed import as_completed

        tag = uuid.uuid4().hex[:8]  # keys of this session's tasks, unique on a shared scheduler
        futures = {}
        for job_id, args in jobs:
            f = self.client.submit(fn, *args, key=f"needle_sim-{label.replace(' ', '_')}-{job_id}-{tag}", pure=False)
            futures[f] = job_id
        progress = Progress(len(futures), label)
        try:
            for f in as_completed(list(futures)):
                job_id = futures.pop(f)
                try:
                    result = f.result()
                except Exception as e:  # KilledWorker (its worker died too often), or a bug
                    result = e
                on_result(job_id, result)
                progress.tick(result)
        except BaseException:
            for f in futures:
                f.cancel()
            raise
        finally:
            progress.close()

    def close(self):
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


def _clock(s):
    if not math.isfinite(s):
        return "?"
    s = int(round(s))
    return f"{s // 3600}h{s % 3600 // 60:02d}m{s % 60:02d}s" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


class Progress:
    """`ensemble: 12/64 runs (11 ok, 1 failed), 0.45/s, 26 s, ETA 1m55s` on stderr: redrawn in
    place on a terminal, a line every 10 s (and at the end) otherwise."""

    def __init__(self, total, label):
        self.total, self.label = total, label
        self.done = self.ok = 0
        self.t0 = self.last = time.monotonic()
        self.tty = sys.stderr.isatty()
        if total:
            self._show(force=True)

    def tick(self, result):
        self.done += 1
        self.ok += isinstance(result, dict) and result.get("status") == "ok"
        self._show(force=self.done == self.total)

    def _show(self, force=False):
        now = time.monotonic()
        if not force and not self.tty and now - self.last < 10:
            return
        self.last = now
        el = now - self.t0
        rate = self.done / el if el > 0 else 0
        eta = (self.total - self.done) / rate if rate > 0 else math.inf
        line = (f"ensemble: {self.done}/{self.total} {self.label} ({self.ok} ok, {self.done - self.ok} failed), "
                f"{rate:.2f}/s, {_clock(el)}, ETA {_clock(eta) if self.done < self.total else '0m00s'}")
        sys.stderr.write(("\r" + line + "\x1b[K") if self.tty else line + "\n")
        sys.stderr.flush()

    def close(self):
        if self.tty and self.total:
            sys.stderr.write("\n")

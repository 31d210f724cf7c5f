"""A real distributed run: a Dask scheduler and two worker processes started on localhost with
Dask's own commands, an ensemble through --scheduler, and one worker killed (SIGKILL) while it
runs a sample: that sample is run again on the other worker, every sample completes exactly
once, and the killed worker's needle_sim process dies with it."""
import json
import os
import re
import signal
import subprocess
import time
import unittest

import psutil

import helpers
from helpers import BASE, SCENE, out_dir, rows


def _wait(cond, seconds, what):
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        v = cond()
        if v:
            return v
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what}")


def _address(sched_file):
    try:
        with open(sched_file) as f:
            return json.load(f)["address"]
    except (OSError, ValueError, KeyError):
        return None


class Distributed(unittest.TestCase):
    def setUp(self):
        self.out = out_dir("distributed")
        os.makedirs(self.out)
        self.procs = []
        sched_file = os.path.join(self.out, "scheduler.json")
        self.procs.append(subprocess.Popen(["/usr/bin/dask", "scheduler", "--host", "127.0.0.1", "--port", "0",
                                            "--no-dashboard", "--scheduler-file", sched_file],
                                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        # The scheduler writes its file in place: it can exist before it holds the JSON.
        self.address = _wait(lambda: _address(sched_file), 30, "the scheduler's address")
        # No nanny: a killed worker stays dead, its tasks must go to the other one.
        self.workers = [subprocess.Popen(["/usr/bin/dask", "worker", self.address, "--nthreads", "1", "--no-nanny",
                                          "--no-dashboard", "--name", f"w{i}"],
                                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) for i in range(2)]
        self.procs += self.workers

    def tearDown(self):
        for p in self.procs:
            if p.poll() is None:
                p.terminate()
        for p in self.procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()

    def test_killed_worker_loses_nothing(self):
        study = os.path.join(self.out, "study")
        # 6 samples of 1.5 s simulated (about 0.6 s of run each)
        p = subprocess.Popen(["/usr/bin/python3", helpers.SCRIPT, "--tool", helpers.TOOL, SCENE, "--samples", "6",
                              "--seed", "2", "--vary", "interaction.friction=uniform(0.02,0.1)", "--scheduler",
                              self.address, "--no-plot", "--out", study] + BASE + ["--set", "time.duration=1.5"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            def busy_worker():
                # a worker running a sample (not a preflight run): its needle_sim child
                for w in self.workers:
                    for c in psutil.Process(w.pid).children():
                        try:
                            m = re.search(r"/\.run(\d+)\.", " ".join(c.cmdline()))
                        except psutil.NoSuchProcess:
                            continue
                        if m:
                            return w, c, int(m.group(1))
                return None

            worker, child, run_id = _wait(busy_worker, 90, "a worker running a sample")
            worker.send_signal(signal.SIGKILL)
            worker.wait(timeout=10)
            # The harness's patience, not an assertion: the sanitized tool runs each sample
            # several times slower (the study took over 120 s once under ASan on CI's machine).
            err = p.communicate(timeout=360 if "/asan/" in helpers.TOOL else 120)[1]
        finally:
            if p.poll() is None:
                p.kill()
        self.assertEqual(p.returncode, 0, err)
        table = rows(os.path.join(study, "ensemble.csv"))
        self.assertEqual(sorted(int(r["run"]) for r in table), list(range(6)), "every sample exactly once")
        self.assertTrue(all(r["status"] == "ok" for r in table), table)
        retried = next(r for r in table if int(r["run"]) == run_id)
        self.assertNotEqual(retried["worker"].split(":")[-1], str(worker.pid), "run again on the surviving worker")
        # the killed worker's run died with it (PR_SET_PDEATHSIG): no orphan left computing
        _wait(lambda: not child.is_running() or child.status() == psutil.STATUS_ZOMBIE, 10, "the orphaned run to die")


if __name__ == "__main__":
    unittest.main()

"""Ensembles on a real Dask LocalCluster with the real tool, on the phantom insertion cut short:
a study with samples that fail numerically, its rows against direct runs (bit for bit), its
summary against its rows; an interrupted study resumed; bad input refused before any run;
`needle_sim ensemble` handing over to the script."""
import json
import os
import signal
import subprocess
import time
import unittest

import numpy as np

import helpers
from helpers import BASE, SCENE, ensemble, out_dir, rows


class Study(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        # 6 samples; gravity's z component 0 or -1e12 m/s^2 (LHS: 3 each): the latter diverges
        # at the first step (exit 3), a sample failure that must not stop the study.
        cls.out = out_dir("study")
        cls.p = ensemble([SCENE, "--samples", "6", "--seed", "5", "--vary", "tissue.material.young=lognormal(1e7,2)",
                          "--vary", "interaction.friction=uniform(0.02,0.1)", "--vary", "tissue.gravity.2=choice(0,-1e12)",
                          "--workers", "2", "--keep-runs", "--out", cls.out] + BASE)
        cls.rows = rows(os.path.join(cls.out, "ensemble.csv")) if cls.p.returncode == 0 else []

    def test_every_sample_recorded_once_failures_with_their_message(self):
        self.assertEqual(self.p.returncode, 0, self.p.stderr)
        self.assertEqual(sorted(int(r["run"]) for r in self.rows), list(range(6)))
        failed = [r for r in self.rows if r["tissue.gravity.2"] == "-1e12"]
        self.assertEqual(len(failed), 3)
        for r in failed:
            self.assertEqual((r["status"], r["exit_code"]), ("numerical_failure", "3"))
            self.assertIn("divergence", r["message"])
            self.assertEqual(r["target_u_final"], "")
        for r in self.rows:
            if r["tissue.gravity.2"] == "0":
                self.assertEqual(r["status"], "ok", r["message"])
        self.assertIn("warning: preflight", self.p.stderr)  # the corner with -1e12 failed numerically
        self.assertIn("ETA", self.p.stderr)

    def test_rows_equal_direct_runs_bit_for_bit(self):
        # The samples table of study.json's seed, and a direct run of one ok row's values
        with open(os.path.join(self.out, "samples.csv")) as f:
            planned = f.read()
        self.assertIn(self.rows[0]["tissue.material.young"], planned)
        r = next(r for r in self.rows if r["status"] == "ok")
        sets = ["--set", f"tissue.material.young={r['tissue.material.young']}", "--set",
                f"interaction.friction={r['interaction.friction']}", "--set", f"tissue.gravity.2={r['tissue.gravity.2']}"]
        d = out_dir("direct")
        subprocess.run([helpers.TOOL, "run", SCENE, "--out", d, "--quiet"] + BASE + sets, check=True, stdout=subprocess.DEVNULL)
        with open(os.path.join(d, "summary.json")) as f:
            s = json.load(f)
        t = s["targets"]["T"]
        self.assertEqual(float(r["target_u_final"]), t["displacement_norm"])
        self.assertEqual(float(r["target_motion_final"]), t["motion_since_start"])
        self.assertEqual([float(r[f"target_{a}"]) for a in "xyz"], t["position"])
        self.assertEqual(float(r["tip_distance_needle"]), t["tip_distance"]["needle"])
        series = rows(os.path.join(d, "timeseries.csv"))
        self.assertEqual(float(r["target_u_max"]), max(float(x["T_u"]) for x in series))
        force = max(np.linalg.norm([float(x[f"needle_holder_f{a}"]) for a in "xyz"]) for x in series)
        self.assertEqual(float(r["force_peak_needle"]), force)
        # --keep-runs kept that run's folder: the same summary
        with open(os.path.join(self.out, "runs", f"{int(r['run']):05d}", "summary.json")) as f:
            self.assertEqual(json.load(f)["targets"], s["targets"])

    def test_summary_consistent_with_rows(self):
        with open(os.path.join(self.out, "summary.json")) as f:
            s = json.load(f)
        ok = [r for r in self.rows if r["status"] == "ok"]
        self.assertEqual(s["statuses"], {"ok": 3, "numerical_failure": 3})
        self.assertEqual(s["seed"], 5)
        v = np.array([float(r["target_u_max"]) for r in ok])
        o = s["outputs"]["target_u_max"]
        self.assertEqual(o["count"], 3)
        self.assertAlmostEqual(o["mean"], v.mean(), delta=1e-15)
        self.assertAlmostEqual(o["std"], v.std(ddof=1), delta=1e-15)
        self.assertAlmostEqual(o["p50"], np.median(v), delta=1e-15)
        pts = np.array([[float(r[f"target_{a}"]) for a in "xyz"] for r in ok])
        np.testing.assert_allclose(s["target_final_position"]["mean"], pts.mean(axis=0), rtol=1e-14)
        np.testing.assert_allclose(s["target_final_position"]["covariance"], np.cov(pts.T), rtol=1e-10, atol=1e-30)
        # softer tissue, larger target motion: a rank correlation of -1 over the ok samples
        self.assertEqual(s["sensitivity"]["spearman"]["tissue.material.young"]["target_u_max"]["spearman"], -1.0)
        for f in ("histograms.png", "outputs_vs_keys.png", "target_ellipse.png"):
            self.assertGreater(os.path.getsize(os.path.join(self.out, f)), 10000, f)


class Resume(unittest.TestCase):
    def test_interrupted_study_resumes_with_only_the_missing_runs(self):
        out = out_dir("resume")
        args = [SCENE, "--samples", "10", "--seed", "9", "--vary", "interaction.friction=uniform(0.02,0.1)",
                "--workers", "1", "--no-plot", "--out", out] + BASE
        p = subprocess.Popen(["/usr/bin/python3", helpers.SCRIPT, "--tool", helpers.TOOL] + args,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        csv_path = os.path.join(out, "ensemble.csv")
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and p.poll() is None:
            if os.path.exists(csv_path) and len(rows(csv_path)) >= 3:
                break
            time.sleep(0.02)
        p.send_signal(signal.SIGINT)  # Ctrl-C mid-study
        err = p.communicate(timeout=60)[1]
        self.assertEqual(p.returncode, 130, err)
        self.assertIn("--resume", err)
        with open(csv_path) as f:
            before = f.read()
        done = len(rows(csv_path))
        self.assertTrue(3 <= done < 10, done)
        with open(csv_path, "a") as f:
            f.write("9,design,9,scene,0.05,o")  # a record cut by a kill: not a result
        r = ensemble(["--resume", "--out", out])
        self.assertEqual(r.returncode, 0, r.stderr)
        self.assertIn(f"{done} of 10 runs recorded, running the {10 - done} missing", r.stderr)
        self.assertIn(f"{10 - done}/{10 - done} runs", r.stderr)
        with open(csv_path) as f:
            after = f.read()
        self.assertTrue(after.startswith(before), "the rows recorded before the interruption are kept as they were")
        self.assertEqual(sorted(int(x["run"]) for x in rows(csv_path)), list(range(10)))
        self.assertTrue(all(x["status"] == "ok" for x in rows(csv_path)))
        # resumed again: nothing to run, and a changed definition is refused
        again = ensemble(["--resume", "--out", out])
        self.assertIn("running the 0 missing", again.stderr)
        changed = ensemble(["--resume", "--samples", "12", "--out", out])
        self.assertEqual(changed.returncode, 2)
        self.assertIn("samples", changed.stderr)


class BadInput(unittest.TestCase):
    def refused(self, args, words):
        out = out_dir("bad")
        p = ensemble(args + ["--out", out])
        self.assertEqual(p.returncode, 2, p.stderr)
        self.assertIn(words, p.stderr)
        self.assertFalse(os.path.exists(os.path.join(out, "ensemble.csv")), "refused before any run")

    def test_command_line(self):
        self.refused([SCENE, "--samples", "4", "--vary", "tissue.material.young=gauss(1,2)"], "unknown distribution 'gauss'")
        self.refused([SCENE, "--samples", "4", "--vary", "tissue.material.young"], "expected KEY=DIST")
        self.refused([SCENE, "--samples", "4", "--vary", "tissue.material.young=normal(1e7)"], "takes 2 parameters")
        self.refused(["no_such_scene.yaml", "--samples", "4", "--vary", "a=uniform(0,1)"], "no_such_scene.yaml: no such file")
        self.refused([SCENE, "--vary", "a=uniform(0,1)"], "--samples N is required")
        self.refused([SCENE, "--samples", "4", "--vary", "tissue.material.young=lognormal(1e7,2)", "--scheduler",
                      "tcp://127.0.0.1:9", "--connect-timeout", "2"], "cannot connect")
        empty = os.path.join(out_dir("empty"), "t.yaml")
        os.makedirs(os.path.dirname(empty))
        open(empty, "w").close()
        self.refused([SCENE, "--trajectories", empty], "no trajectories")

    def test_scene_keys_checked_by_the_tool_before_any_run(self):
        # An unknown key, and a normal that reaches negative Young's moduli at its lowest sample
        self.refused([SCENE, "--samples", "4", "--seed", "1", "--workers", "1", "--vary",
                      "tissue.material.yung=uniform(1e6,1e7)"] + BASE, "'tissue.material.yung'")
        self.refused([SCENE, "--samples", "20", "--seed", "1", "--workers", "1", "--vary",
                      "tissue.material.young=normal(1e7,1e7)"] + BASE, "'tissue.material.young': must be > 0")


class ToolHandsOver(unittest.TestCase):
    def test_needle_sim_ensemble(self):
        h = subprocess.run([helpers.TOOL, "ensemble", "--help"], capture_output=True, text=True)
        self.assertEqual(h.returncode, 0, h.stderr)
        self.assertIn("usage: needle_sim ensemble", h.stdout)
        # Without a sourced environment the tool hands over to its own package (devel space).
        bare = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "ROS_PACKAGE_PATH")}
        h = subprocess.run([helpers.TOOL, "ensemble", "--help"], capture_output=True, text=True, env=bare)
        self.assertEqual(h.returncode, 0, h.stderr)
        out = out_dir("tool")
        # with the target's error bound (needle_sim run --target-error), every 100th step
        p = subprocess.run([helpers.TOOL, "ensemble", SCENE, "--samples", "2", "--seed", "1", "--workers", "1", "--no-plot",
                            "--vary", "interaction.friction=uniform(0.02,0.1)", "--target-error-every", "100",
                            "--out", out] + BASE,
                           capture_output=True, text=True, env={k: v for k, v in os.environ.items() if k != "NEEDLE_SIM_TOOL"})
        self.assertEqual(p.returncode, 0, p.stderr)
        with open(os.path.join(out, "study.json")) as f:
            self.assertEqual(os.path.realpath(json.load(f)["tool"]), os.path.realpath(helpers.TOOL))  # the tool runs itself
        table = rows(os.path.join(out, "ensemble.csv"))
        self.assertEqual([r["status"] for r in table], ["ok", "ok"])
        self.assertTrue(all(float(r["error_bound"]) > 0 for r in table), table)
        with open(os.path.join(out, "summary.json")) as f:
            self.assertEqual(json.load(f)["outputs"]["error_bound"]["count"], 2)


if __name__ == "__main__":
    unittest.main()

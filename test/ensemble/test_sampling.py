"""The ensemble's sampling, statistics and trajectories, without runs: distributions against
their known quantiles, seeded designs, Latin-hypercube strata, the Saltelli blocks, the Sobol
index estimator on a function with known indices, DBS entry points turned into base poses."""
import math
import os
import unittest

import numpy as np

import helpers
from needle_sim.ensemble import design, statistics, trajectories
from needle_sim.ensemble.distributions import UsageError, parse_all, parse_vary
from needle_sim.scene_check import check


class Distributions(unittest.TestCase):
    def test_known_quantiles(self):
        # normal: mu + 1.959964 sigma at 97.5 %
        self.assertAlmostEqual(parse_vary("a=normal(10,2)").quantile(0.975), 10 + 2 * 1.959963985, places=6)
        # lognormal(median, factor): the median, and median x factor one sigma up (84.13 %)
        ln = parse_vary("tissue.material.young=lognormal(6000,2)")
        self.assertAlmostEqual(ln.quantile(0.5), 6000.0, places=6)
        self.assertAlmostEqual(ln.quantile(0.5 * (1 + math.erf(1 / math.sqrt(2)))), 12000.0, places=4)
        self.assertAlmostEqual(ln.quantile(0.95), 6000 * 2 ** 1.644853627, places=3)
        u = parse_vary("b=uniform(1,3)")
        self.assertAlmostEqual(u.quantile(0.25), 1.5)
        c = parse_vary("c=choice(block,gauss_seidel,x)")
        self.assertEqual(c.ppf([0.0, 0.34, 0.99, 0.6666]), ["block", "gauss_seidel", "x", "gauss_seidel"])

    def test_sampled_quantiles_match(self):
        # 2000 Latin-hypercube values of each key: their percentiles within 1 % of the exact ones
        dists = parse_all(["y=lognormal(6000,2)", "n=normal(0.45,0.01)", "f=uniform(0.02,0.1)"])
        d = design.make_design(dists, 2000, "lhs", 7)
        for j, dist in enumerate(dists):
            v = np.array([row[j] for row in d.values])
            for q in (5, 50, 95):
                exact = dist.quantile(q / 100)
                self.assertAlmostEqual(np.percentile(v, q) / exact, 1.0, delta=0.01, msg=f"{dist.key} p{q}")

    def test_bad_distributions(self):
        for text, words in [("k=gauss(1,2)", "unknown distribution 'gauss'"), ("k", "expected KEY=DIST"),
                            ("k=normal(1)", "takes 2 parameters"), ("k=normal(1,-2)", "sigma must be > 0"),
                            ("k=lognormal(6000,1)", "factor > 1"), ("k=uniform(3,1)", "a < b"),
                            ("k=normal(1,x)", "not a finite number"), ("k=normal 1,2", "NAME(ARGS)"),
                            ("a..b=normal(1,2)", "not a scene key path"), ("k=choice()", "at least one value")]:
            with self.assertRaises(UsageError, msg=text) as cm:
                parse_vary(text)
            self.assertIn(words, str(cm.exception))
        with self.assertRaises(UsageError):
            parse_all(["k=normal(1,2)", "k=uniform(0,1)"])


class Designs(unittest.TestCase):
    dists = parse_all(["a=uniform(0,1)", "b=normal(0,1)", "c=choice(x,y)"])

    def test_seeded_repeatable(self):
        one = design.make_design(self.dists, 16, "lhs", 42).values
        self.assertEqual(one, design.make_design(self.dists, 16, "lhs", 42).values)
        self.assertNotEqual(one, design.make_design(self.dists, 16, "lhs", 43).values)
        self.assertEqual(design.make_design(self.dists, 8, "sobol", 5).values, design.make_design(self.dists, 8, "sobol", 5).values)

    def test_lhs_strata_each_hit_once(self):
        n = 37
        d = design.make_design(self.dists, n, "lhs", 1)
        for j in range(len(self.dists)):
            strata = sorted(int(r[2][j] * n) for r in d.rows)
            self.assertEqual(strata, list(range(n)))

    def test_sobol_needs_power_of_two(self):
        with self.assertRaises(UsageError):
            design.make_design(self.dists, 10, "sobol", 1)

    def test_saltelli_blocks(self):
        n, k = 8, len(self.dists)
        d = design.make_design(self.dists, n, "saltelli", 3)
        self.assertEqual(len(d), n * (k + 2))
        blocks = {}
        for block, i, u in d.rows:
            blocks.setdefault(block, {})[i] = u
        for j, dist in enumerate(self.dists):
            for i in range(n):
                ab = blocks[f"AB:{dist.key}"][i]
                expect = blocks["A"][i].copy()
                expect[j] = blocks["B"][i][j]
                np.testing.assert_array_equal(ab, expect)

    def test_sobol_indices_known_answer(self):
        # Y = X1 + 2 X2 (X uniform on [0, 1], independent): S1 = 1/5, S2 = 4/5, no interaction (S = ST)
        dists = parse_all(["x1=uniform(0,1)", "x2=uniform(0,1)"])
        d = design.make_design(dists, 1024, "saltelli", 11)
        rows = [{"block": b, "sample": str(i), "x1": repr(v[0]), "x2": repr(v[1]), "y": repr(v[0] + 2 * v[1]),
                 "status": "ok", "trajectory": "scene"} for (b, i, _), v in zip(d.rows, d.values)]
        s = statistics.summarize(rows, ["x1", "x2"], ["x1", "x2"], ["y"], ["scene"], saltelli=True)
        sob = s["sensitivity"]["sobol"]
        for key, exact in (("x1", 0.2), ("x2", 0.8)):
            self.assertAlmostEqual(sob[key]["y"]["first_order"], exact, delta=0.05)
            self.assertAlmostEqual(sob[key]["y"]["total"], exact, delta=0.05)
        self.assertGreater(s["sensitivity"]["spearman"]["x2"]["y"]["spearman"], s["sensitivity"]["spearman"]["x1"]["y"]["spearman"])


class Trajectories(unittest.TestCase):
    """The --trajectories file's poses, computed by the tool (`needle_sim check --aim`)."""
    scene_file = os.path.join(helpers.ROOT, "config", "scenes", "dbs_coarse.yaml")

    @classmethod
    def setUpClass(cls):
        cls.scene = check(helpers.TOOL, cls.scene_file)

    def write(self, text):
        path = os.path.join(helpers.out_dir("trajectories"), "t.yaml")
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(path, "w") as f:
            f.write(text)
        return path

    def poses(self, t):
        out = {}
        for s in t.sets:
            k, v = s.split("=")
            out[k] = np.array([float(x) for x in v.strip("[]").split(",")])
        return out

    def test_entry_points_aim_the_tool_at_the_target(self):
        # The scene's own line (its tip at rest -> its planned final tip) gives back its poses;
        # another entry turns cannula and electrode as one: tips end on the target, axis along
        # entry -> target, the electrode's base 10 mm behind the cannula's on that axis.
        needles = self.scene["needles"]
        start = np.array(needles[0]["rest_tip"])
        target = [-11.1, -12.9, -7.7]
        path = self.write(f"units: mm\nneedles: [cannula, electrode]\ntrajectories:\n"
                          f"  - {{name: scene, entry: {list(start * 1e3)}}}\n"
                          f"  - {{name: lateral, entry: [-36, 20, 62], target: {target}}}\n"
                          f"  - {{name: raw, set: {{interaction.friction: 0.1}}}}\n")
        t = trajectories.load(path, helpers.TOOL, self.scene_file)
        self.assertEqual([x.name for x in t], ["scene", "lateral", "raw"])
        same = self.poses(t[0])
        for n in needles:
            np.testing.assert_allclose(same[f"{n['set_prefix']}.base.position"], n["base_position"], rtol=0, atol=1e-9)
            np.testing.assert_allclose(same[f"{n['set_prefix']}.base.direction"], n["base_direction"], rtol=0, atol=1e-12)
        p = self.poses(t[1])
        axis = np.array(target) - np.array([-36, 20, 62])
        axis /= np.linalg.norm(axis)
        # The cannula's tip (base + advance x axis + length x unit axis, as the tool moves it)
        # ends exactly on the target; the electrode's within the scene's 6-digit coordinates
        # of its base (1 um), as in the scene itself.
        for prefix, length, tol in (("needles.0", 0.12, 1e-12), ("needles.1", 0.13, 2e-6)):
            d = p[f"{prefix}.base.direction"]
            self.assertAlmostEqual(np.linalg.norm(d), 1.0, delta=1e-6)  # as the scene's (6 digits)
            np.testing.assert_allclose(d / np.linalg.norm(d), axis, rtol=0, atol=1e-12)
            np.testing.assert_allclose(p[f"{prefix}.base.position"] + 0.0872 * d + length * d / np.linalg.norm(d),
                                       np.array(target) * 1e-3, rtol=0, atol=tol)
        np.testing.assert_allclose(p["needles.0.base.position"] - p["needles.1.base.position"], 0.01 * axis, rtol=0, atol=2e-6)
        self.assertAlmostEqual(t[1].info["entry_target_distance"], np.linalg.norm(np.array(target) - [-36, 20, 62]) * 1e-3)
        self.assertEqual(t[2].sets, ["interaction.friction=0.1"])
        # The tool's loader, given the computed overrides, puts the planned final tip on the target.
        aimed = check(helpers.TOOL, self.scene_file, t[1].sets)
        np.testing.assert_allclose(aimed["needles"][0]["planned_tip"], np.array(target) * 1e-3, rtol=0, atol=1e-12)

    def test_the_study_set_is_the_scene_aimed(self):
        # The poses are those of the scene as the study runs it, --set applied: a cannula
        # advanced 2.8 mm farther starts that much farther back, its tip still ending on the target.
        target = [-11.1, -12.9, -7.7]
        sets = ["needles.0.motion.1.advance=0.09"]
        path = self.write(f"units: mm\ntarget: {target}\ntrajectories: [{{name: a, entry: [-36, 20, 62]}}]\n")
        t = trajectories.load(path, helpers.TOOL, self.scene_file, sets)
        aimed = check(helpers.TOOL, self.scene_file, sets + t[0].sets)
        np.testing.assert_allclose(aimed["needles"][0]["planned_tip"], np.array(target) * 1e-3, rtol=0, atol=1e-12)

    def test_bad_files(self):
        for text, words in [("", "no trajectories"), ("[]", "no trajectories"), ("trajectories: []", "no trajectories"),
                            ("- {name: a}", "give 'entry'"), ("- {entry: [1, 2]}", "three numbers"),
                            ("needles: [drill]\ntrajectories: [{entry: [0,0,0]}]", "no needle 'drill'"),
                            ("- {name: a, entry: [0,0,0]}\n- {name: a, entry: [0,0,1]}", "used twice"),
                            ("units: inch\ntrajectories: [{entry: [0,0,0]}]", "units 'inch'"),
                            ("- {entri: [0,0,0]}", "unknown key 'entri'"),
                            ("- {name: a, entry: [0,0,0], target: [0,0,0]}", "the entry point and the target coincide")]:
            with self.assertRaises(UsageError, msg=text) as cm:
                trajectories.load(self.write(text), helpers.TOOL, self.scene_file)
            self.assertIn(words, str(cm.exception))


if __name__ == "__main__":
    unittest.main()

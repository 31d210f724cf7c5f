"""The plots' labels name what the runs were (issue #42: plot_probes labelled two different
runs "675 DOFs", the adaptive run's DOFs after it had coarsened back)."""
import csv
import json
import os
import tempfile
import unittest

from needle_sim.plots import probes, run


def write_run(root, name, dofs_per_step):
    d = os.path.join(root, name)
    os.makedirs(d)
    with open(os.path.join(d, "summary.json"), "w") as f:
        json.dump({"scene": {"name": name}, "tissue": {"dofs": dofs_per_step[-1]},
                   "names": {"probes": ["p1"], "needles": [], "targets": []}}, f)
    with open(os.path.join(d, "timeseries.csv"), "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["step", "dofs", "p1_ux", "p1_uy", "p1_uz"])
        for k, n in enumerate(dofs_per_step):
            w.writerow([k + 1, n, 1e-4 * k, 0, 0])
    return d


class ProbeLabels(unittest.TestCase):
    def test_an_adaptive_run_is_labelled_with_its_largest_mesh(self):
        with tempfile.TemporaryDirectory() as root:
            uniform = probes.load(write_run(root, "phantom_insertion_8x4x4", [675, 675, 675]))
            adaptive = probes.load(write_run(root, "phantom_insertion_adaptive", [675, 2781, 675]))
            self.assertEqual(uniform["dofs"], "675")
            self.assertEqual(adaptive["dofs"], "up to 2,781")
            self.assertEqual(adaptive["name"], "phantom_insertion_adaptive")


class RunPanels(unittest.TestCase):
    def test_a_scene_without_probes_shows_its_targets_labelled_as_targets(self):
        dbs = {"names": {"probes": [], "targets": ["STN_L", "STN_R"], "needles": ["cannula"]}}
        self.assertEqual(run.top_panel(dbs), (["STN_L", "STN_R"], 1e3, "target |u| from rest [mm]"))
        phantom = {"names": {"probes": ["p1", "p2"], "targets": ["T"], "needles": ["needle"]}}
        self.assertEqual(run.top_panel(phantom), (["p1", "p2"], 1e6, "probe |u| [µm]"))


if __name__ == "__main__":
    unittest.main()

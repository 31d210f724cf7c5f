"""The Python package needle_sim (src/needle_sim) as a user imports it (#36): every module
from the environment the test runs in, with no sys.path tricks (CTest: the catkin devel
space's environment, or the source tree on PYTHONPATH in the plain build, as `pip install
-e .` gives it); in the catkin build, the generated needle_sim.msg, .srv and .cfg beside its
modules in the one package; the executables in scripts/ only call a module's main()."""
import ast
import importlib
import importlib.util
import os
import pkgutil
import unittest

import needle_sim

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
ROS_BUILD = os.environ.get("NEEDLE_SIM_ROS_BUILD") == "1"
GENERATED = ("msg", "srv", "cfg")  # catkin's message and dynamic_reconfigure generation


def modules():
    return sorted(m.name for m in pkgutil.walk_packages(needle_sim.__path__, "needle_sim."))


def python_files(*folders):
    for folder in folders:
        for d, _, files in os.walk(os.path.join(ROOT, folder)):
            yield from (os.path.join(d, f) for f in files if f.endswith(".py"))


class Package(unittest.TestCase):
    def test_every_module_imports(self):
        import needle_sim.ensemble  # noqa: F401  (what `needle_sim ensemble` runs)

        names = modules()
        for expected in ("needle_sim.ensemble.cli", "needle_sim.ensemble.trajectories", "needle_sim.paths",
                         "needle_sim.scene_check", "needle_sim.run_outputs", "needle_sim.studies.runs",
                         "needle_sim.studies.dbs", "needle_sim.plots.run", "needle_sim.nodes.insertion_publisher",
                         "needle_sim.devtools.scene_keys_doc"):
            self.assertIn(expected, names)
        for name in names:
            if name.endswith(".__main__"):
                continue  # runs the program
            if not ROS_BUILD and name.split(".")[1] == "nodes":
                continue  # rospy and the generated messages: the catkin build only
            with self.subTest(module=name):
                importlib.import_module(name)

    def test_modules_are_the_source_trees(self):
        # devel space and `pip install -e .`: the modules are the checkout's, not copies
        import needle_sim.ensemble.cli

        self.assertEqual(os.path.dirname(os.path.dirname(needle_sim.ensemble.cli.__file__)),
                         os.path.join(ROOT, "src", "needle_sim"))

    @unittest.skipUnless(ROS_BUILD, "the catkin build generates the messages")
    def test_generated_messages_are_in_the_same_package(self):
        from needle_sim.cfg import LimitsConfig  # noqa: F401
        from needle_sim.msg import InsertNeedleAction, SimStatus  # noqa: F401
        from needle_sim.srv import PredictInsertion, SetTarget, SteerToTarget  # noqa: F401

        self.assertTrue({"needle_sim.msg", "needle_sim.srv", "needle_sim.cfg"} <= set(modules()))
        self.assertEqual(SimStatus._type, "needle_sim/SimStatus")

    def test_no_sys_path_manipulation(self):
        # Neither the package, nor the scripts, nor the Python tests reach for sys.path.
        for path in python_files(os.path.join("src", "needle_sim"), "scripts", os.path.join("test", "ensemble"),
                                 os.path.join("test", "python")):
            with open(path) as f:
                tree = ast.parse(f.read(), path)
            for node in ast.walk(tree):
                if isinstance(node, ast.Attribute) and node.attr == "path" and getattr(node.value, "id", "") == "sys":
                    self.fail(f"{os.path.relpath(path, ROOT)}:{node.lineno}: sys.path")

    def test_scripts_only_call_a_modules_main(self):
        scripts = sorted(f for f in os.listdir(os.path.join(ROOT, "scripts")) if f.endswith(".py"))
        self.assertIn("ensemble.py", scripts)
        for name in scripts:
            with self.subTest(script=name), open(os.path.join(ROOT, "scripts", name)) as f:
                tree = ast.parse(f.read(), name)
                imports = [n for n in tree.body if isinstance(n, ast.ImportFrom)]
                self.assertEqual(len(imports), 1, "one `from needle_sim.X import main`")
                self.assertTrue(imports[0].module.startswith("needle_sim."))
                self.assertEqual([a.name for a in imports[0].names], ["main"])
                self.assertIsNotNone(importlib.util.find_spec(imports[0].module))
                self.assertFalse([n for n in tree.body if isinstance(n, (ast.FunctionDef, ast.ClassDef, ast.Assign))])


if __name__ == "__main__":
    unittest.main()

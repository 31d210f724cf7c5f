"""needle_sim's Python: the programs around the needle_sim tool and the ROS node (README.md,
"The Python package"). One concept a module; every program's code is here, the executables
in scripts/ only call a module's main():

  paths        where the share folder (scenes, meshes) and the needle_sim tool are
  scene_check  what the tool's loader made of a scene (`needle_sim check --json`, --aim)
  run_outputs  what a `needle_sim run` folder holds (summary.json, timeseries.csv)
  ensemble     `needle_sim ensemble`: many runs on a Dask cluster (doc/ensemble.md)
  studies      the studies and sweeps (doc/benchmarks.md, doc/verification.md)
  plots        plots of runs and calibrations
  nodes        ROS programs: the scripted insertion, node benchmarks, launch helpers
  devtools     the source tree's tools: scene_format.md's key tables, the scene regression

catkin's message generation adds needle_sim.msg, needle_sim.srv and needle_sim.cfg beside
them (catkin_python_setup in CMakeLists.txt). Nothing is imported here: in a devel space
this file runs inside catkin's generated needle_sim/__init__.py.
"""

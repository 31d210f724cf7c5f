#!/usr/bin/python3
"""Behaviour regression of every shipped scene, before and after a refactor.
The program is needle_sim.devtools.scene_regression (README.md, "The Python package")."""
import sys

from needle_sim.devtools.scene_regression import main

if __name__ == "__main__":
    sys.exit(main())

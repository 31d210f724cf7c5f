#!/usr/bin/python3
"""Plots of a steering run: cut paths and tip paths.
The program is needle_sim.plots.tip_path (README.md, "The Python package")."""
import sys

from needle_sim.plots.tip_path import main

if __name__ == "__main__":
    sys.exit(main())

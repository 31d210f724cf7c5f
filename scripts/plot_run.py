#!/usr/bin/python3
"""Plots of one `needle_sim run` folder.
The program is needle_sim.plots.run (README.md, "The Python package")."""
import sys

from needle_sim.plots.run import main

if __name__ == "__main__":
    sys.exit(main())

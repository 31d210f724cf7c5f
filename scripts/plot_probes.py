#!/usr/bin/python3
"""Probe displacement against step for several runs.
The program is needle_sim.plots.probes (README.md, "The Python package")."""
import sys

from needle_sim.plots.probes import main

if __name__ == "__main__":
    sys.exit(main())

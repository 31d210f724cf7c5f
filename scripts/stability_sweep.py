#!/usr/bin/python3
"""Stability sweep of the phantom insertion (issue #8; CTest stability_sweep_quick).
The program is needle_sim.studies.stability_sweep (README.md, "The Python package")."""
import sys

from needle_sim.studies.stability_sweep import main

if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/python3
"""Plot of a calibration (`needle_sim calibrate` runs this script).
The program is needle_sim.plots.calibration (README.md, "The Python package")."""
import sys

from needle_sim.plots.calibration import main

if __name__ == "__main__":
    sys.exit(main())

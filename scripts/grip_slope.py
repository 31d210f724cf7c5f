#!/usr/bin/python3
"""The grip pressure's friction per metre, refined (issue #21).
The program is needle_sim.studies.grip_slope (README.md, "The Python package")."""
import sys

from needle_sim.studies.grip_slope import main

if __name__ == "__main__":
    sys.exit(main())

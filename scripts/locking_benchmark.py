#!/usr/bin/python3
"""The volumetric-locking benchmark (doc/verification.md "Nearly incompressible tissue").
The program is needle_sim.studies.locking (README.md, "The Python package")."""
import sys

from needle_sim.studies.locking import main

if __name__ == "__main__":
    sys.exit(main())

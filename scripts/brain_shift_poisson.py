#!/usr/bin/python3
"""The brain shift against Poisson's ratio (doc/verification.md "Nearly incompressible tissue").
The program is needle_sim.studies.brain_shift (README.md, "The Python package")."""
import sys

from needle_sim.studies.brain_shift import main

if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/python3
"""Verification of the goal-oriented target-error estimate (doc/verification.md).
The program is needle_sim.studies.target_error (README.md, "The Python package")."""
import sys

from needle_sim.studies.target_error import main

if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/python3
"""How far the DBS prediction moves when only the linear solver does (issue #38).
The program is needle_sim.studies.reproducibility (README.md, "The Python package")."""
import sys

from needle_sim.studies.reproducibility import main

if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/python3
"""`needle_sim ensemble`: many runs of a scene with sampled --set values on Dask (doc/ensemble.md); the tool runs this script.
The program is needle_sim.ensemble.cli (README.md, "The Python package")."""
import sys

from needle_sim.ensemble.cli import main

if __name__ == "__main__":
    sys.exit(main())

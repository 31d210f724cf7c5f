#!/usr/bin/python3
"""Run time against probe error, uniform against adaptive meshes (doc/benchmarks.md).
The program is needle_sim.studies.adaptivity (README.md, "The Python package")."""
import sys

from needle_sim.studies.adaptivity import main

if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/python3
"""The deep-brain-stimulation study (doc/benchmarks.md "DBS").
The program is needle_sim.studies.dbs (README.md, "The Python package")."""
import sys

from needle_sim.studies.dbs import main

if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/python3
"""doc/benchmarks.md's tables, measured and written by one program.
The program is needle_sim.devtools.benchmarks (README.md, "The Python package")."""
import sys

from needle_sim.devtools.benchmarks import main

if __name__ == "__main__":
    sys.exit(main())

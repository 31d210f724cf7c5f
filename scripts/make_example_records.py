#!/usr/bin/python3
"""The shipped example recordings (data/examples/, doc/calibration.md).
The program is needle_sim.devtools.make_example_records (README.md, "The Python package")."""
import sys

from needle_sim.devtools.make_example_records import main

if __name__ == "__main__":
    sys.exit(main())

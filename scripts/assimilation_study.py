#!/usr/bin/python3
"""Twin experiments for the online estimation (issue #41).
The program is needle_sim.studies.assimilation (README.md, "The Python package")."""
import sys

from needle_sim.studies.assimilation import main

if __name__ == "__main__":
    sys.exit(main())

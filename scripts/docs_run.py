#!/usr/bin/python3
"""Runs the docs: their command blocks and quoted figures (.ci/run, docs phase).
The program is needle_sim.devtools.docs_run (README.md, "The Python package")."""
import sys

from needle_sim.devtools.docs_run import main

if __name__ == "__main__":
    sys.exit(main())

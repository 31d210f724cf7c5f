#!/usr/bin/python3
"""Removes /use_sim_time when replay.launch ends.
The program is needle_sim.nodes.sim_time_cleanup (README.md, "The Python package")."""
import sys

from needle_sim.nodes.sim_time_cleanup import main

if __name__ == "__main__":
    sys.exit(main())

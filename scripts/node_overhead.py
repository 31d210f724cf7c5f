#!/usr/bin/python3
"""The ROS node's overhead beyond the core step (doc/benchmarks.md).
The program is needle_sim.nodes.node_overhead (README.md, "The Python package")."""
import sys

from needle_sim.nodes.node_overhead import main

if __name__ == "__main__":
    sys.exit(main())

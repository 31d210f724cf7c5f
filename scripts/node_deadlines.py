#!/usr/bin/python3
"""Does the ROS node keep its deadlines? (doc/benchmarks.md).
The program is needle_sim.nodes.node_deadlines (README.md, "The Python package")."""
import sys

from needle_sim.nodes.node_deadlines import main

if __name__ == "__main__":
    sys.exit(main())

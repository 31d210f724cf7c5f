#!/usr/bin/python3
"""Scripted needle insertion for the node (sim.launch scripted:=true).
The program is needle_sim.nodes.insertion_publisher (README.md, "The Python package")."""
import sys

from needle_sim.nodes.insertion_publisher import main

if __name__ == "__main__":
    sys.exit(main())

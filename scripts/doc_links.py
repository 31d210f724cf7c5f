#!/usr/bin/python3
"""The docs' relative links and #anchors exist (CTest doc_links).
The program is needle_sim.devtools.doc_links (README.md, "The Python package")."""
import sys

from needle_sim.devtools.doc_links import main

if __name__ == "__main__":
    sys.exit(main())

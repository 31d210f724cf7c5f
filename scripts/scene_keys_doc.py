#!/usr/bin/python3
"""doc/scene_format.md's key tables from the declarations (CTest scene_format_doc).
The program is needle_sim.devtools.scene_keys_doc (README.md, "The Python package")."""
import sys

from needle_sim.devtools.scene_keys_doc import main

if __name__ == "__main__":
    sys.exit(main())

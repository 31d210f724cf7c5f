"""python3 -m needle_sim.ensemble ARGS: the same as `needle_sim ensemble ARGS`."""
import sys

from .cli import main

sys.exit(main())

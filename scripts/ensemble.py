#!/usr/bin/python3
"""needle_sim ensemble: many `needle_sim run`s of a scene with sampled --set values (material
uncertainty) and base trajectories (entry points), as Dask tasks; the rows in DIR/ensemble.csv,
statistics in DIR/summary.json, plots. Reference: doc/ensemble.md.

`needle_sim ensemble ARGS` runs this script (the tool hands its arguments over), as does
`scripts/ensemble.py ARGS` from a source tree.

Sample runs:
    needle_sim ensemble dbs_coarse.yaml --samples 16 --vary tissue.material.young=lognormal(6000,2) \
        --vary tissue.material.poisson=uniform(0.40,0.49) --seed 1 --out results/dbs_material_small
    needle_sim ensemble dbs_coarse.yaml --trajectories dbs_left_stn_entries.yaml --out results/dbs_entries
    needle_sim ensemble --resume --out results/dbs_material_small
"""
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from needle_sim_ensemble.cli import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())

"""needle_sim ensemble: many `needle_sim run`s of one scene with sampled `--set` values, on a
Dask cluster (doc/ensemble.md). The modules, one concept each:

  distributions  KEY=DIST parsing and the inverse CDFs
  design         the seeded sample table (Latin hypercube, Sobol, Saltelli)
  trajectories   the --trajectories file: base poses as --set overrides (the tool's check --aim)
  run_task       the Dask task: one needle_sim run in a private folder, its numbers
  store          DIR/study.json, the appended ensemble.csv, the atomic summary.json
  statistics     percentiles, the target's covariance, rank correlations, Sobol indices
  plots          histograms, outputs against keys, the target's 95 % ellipses
  engine         the cluster, submission, progress with ETA, faults
  cli            the command line
"""

"""The studies and sweeps: each module a program (main()) that runs the needle_sim tool on
shipped scenes and writes tables and plots under ./results (runs: what they share)."""

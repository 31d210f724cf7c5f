"""Plots of what the needle_sim tool wrote (a run's folder, a calibration's fit.csv); each
module a program (main())."""

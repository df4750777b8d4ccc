"""Reading what users have: calibrations, rectification, TUM trajectories and the dataset readers."""

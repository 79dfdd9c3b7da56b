"""Field data: observed trajectories and station measurements read from files (NGSIM, highD, PeMS, SUMO FCD/E1/E2, generic CSV)."""

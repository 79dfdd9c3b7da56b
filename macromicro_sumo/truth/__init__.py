"""Ground truth: a demand run in SUMO, recorded with detectors."""

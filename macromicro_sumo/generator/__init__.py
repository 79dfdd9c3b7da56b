"""Stage I: the hidden-vehicle generator G_phi, its sampler and its training."""

"""What the stages exchange: recorded truth, snapshots, psi, the macro statistics."""

"""What reaches a robot: solvers for Δθ, the Δθ table, programs, paths, the 500 Hz
controller path and the compensation service's logic."""

"""The domain library: robots, kinematics, frames, identification, the model, training,
solvers, metrics, the twin, I/O. It never imports a stage (pipeline/<stage>.py)."""

"""The domain library, one package per topic: project (settings, artifact paths, columns, writing),
reading (exports, orientation, campaigns, presets, prepared inputs), robot (kinematics, frames,
identification, error maps, TCPs, URDF), sim (the twin), learning (model, loss, training, checkpoint,
metrics, ONNX, sweeps, validation), runtime (solvers, Δθ table, programs, paths, the service), planner
(what to measure) and reporting (the report's page, figures, summary). It never imports a stage or a
command."""

"""The project's plumbing: settings (params.yaml) and their checks, artifact paths, table column
names, files written whole, and how a stage or command ends on bad input."""

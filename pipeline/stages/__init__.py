"""The DVC stages of ./dvc.yaml, one module each (`python -m pipeline.stages.<name>`): each reads its
params and files, calls the library and writes its outputs. No stage imports another, nor a command."""

"""SPI-BoTER calibration pipeline: thin stages (pipeline/<stage>.py, one per DVC stage of dvc.yaml)
and commands (COMMANDS: a module or a package each) over one library (pipeline/lib/), which never
imports them. tests/test_layout.py holds the layout to this."""
import os

# Run by hand (python -m pipeline.<name>, or the spi-boter-<name> script), never by ./dvc.yaml.
COMMANDS = ("bench", "serve", "program", "plan", "fleet", "ablation", "preset", "twin")

# Before numpy loads: BLAS threads on the small matrices here only fight torch's
# threads (measured 5-10x slower calibration with them).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

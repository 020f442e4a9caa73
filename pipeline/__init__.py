"""SPI-BoTER calibration pipeline: thin stages (pipeline/<stage>.py, one per DVC stage) and
commands over one library (pipeline/lib/), which never imports them."""
import os

# Before numpy loads: BLAS threads on the small matrices here only fight torch's
# threads (measured 5-10x slower calibration with them).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

"""SPI-BoTER calibration pipeline: one module per DVC stage plus the pieces they share."""
import os

# Before numpy loads: BLAS threads on the small matrices here only fight torch's
# threads (measured 5-10x slower calibration with them).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

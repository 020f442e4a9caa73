"""SPI-BoTER calibration pipeline: the DVC stages (pipeline/stages/, one module per stage of dvc.yaml)
and the commands run by hand (pipeline/commands/, a module or a package each) over one library
(pipeline/lib/, grouped by topic), which never imports them. tests/test_layout.py holds the layout to this."""
import os
import platform

# Before numpy loads: BLAS threads on the small matrices here only fight torch's
# threads (measured 5-10x slower calibration with them).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# MKL (torch's BLAS and vector math on x86) on one thread: with two, float64 results differed in the last
# bits in about one process in six on the 2-core Xeon (up to 1e-9 mm after one FK), so a fresh clone's
# `dvc repro` could differ from dvc.lock. torch's own intra-op threads stay. Training costs ~1.7x the
# time; a later torch.set_num_threads(n) gives MKL n threads again (sweep jobs with n > 1, benchmarks).
os.environ.setdefault("MKL_NUM_THREADS", "1")
# The same kernels on every x86-64 CPU, Intel or AMD, with or without AVX-512: each numeric library
# otherwise picks its kernels by the CPU it finds, and their last bits differ, so a fresh clone's
# `dvc repro` on an AMD EPYC gave other bytes than dvc.lock made on a Xeon (every output from the frame
# stage on). AVX2 is the widest every x86 machine here has (docs/decisions.md, "The same kernels").
X86 = platform.machine().lower() in ("x86_64", "amd64")
KERNEL_PINS = {"OPENBLAS_CORETYPE": "Haswell",                 # numpy's and scipy's OpenBLAS
               "MKL_CBWR": "AVX2,STRICT",                      # torch's MKL: its reproducible AVX2 branch
               "ATEN_CPU_CAPABILITY": "avx2",                  # torch's own vectorised kernels
               "ONEDNN_MAX_CPU_ISA": "AVX2",                   # oneDNN, under torch
               "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR"}   # numpy's own loops
if X86:
    for name, value in KERNEL_PINS.items():
        os.environ.setdefault(name, value)

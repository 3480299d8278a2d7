"""The running system, one folder per kind, in data-flow order: ``transport`` (how nodes talk), ``nodes`` (the
processes of the data flow), ``sessions`` (whole sessions built from them), ``surfaces`` (what people look at); beside
them the ``msk`` command line (``cli``, ``commands``) and ``bench``."""

import os

# One BLAS thread per process unless the user says otherwise (before anything imports numpy or scipy: OpenBLAS reads
# it when it loads). Our matrices are small (groups x coordinates) and a live session runs many processes; a threaded
# OpenBLAS there only spins for the cores the other processes use. The calibration's L-BFGS-B makes thousands of
# level-1 calls on ~40k-element vectors: the bench press demo subject took 202 s (33 s CPU) with the default threads
# and 18 s (5 s CPU) with one, on the 2 shared cores of a machine running the test suite.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from msk_core import __version__  # noqa: E402 - after the BLAS threads are set

__all__ = ["__version__"]

"""msk-live science core: musculoskeletal models, signal processing and activation estimation.

This package does no device or network I/O and draws nothing: it imports no zenoh, mcap or serial code, no tqdm and
no matplotlib (progress is reported by callback, :mod:`msk_core.progress`; plots and reports are made in services/).
"""

__version__ = "0.1.0"

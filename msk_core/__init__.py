"""msk-live science core: musculoskeletal models, signal processing and activation estimation.

This package does no device or network I/O: it imports no zenoh, mcap or serial code.
"""

__version__ = "0.1.0"

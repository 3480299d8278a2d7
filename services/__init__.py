"""Zenoh nodes (drivers, estimator, recorder, replayer) and the ``msk`` command line."""

from msk_core import __version__

__all__ = ["__version__"]

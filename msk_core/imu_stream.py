"""Moved to msk_core.imu.stream (the tree reads as the data flow); this name stays so existing imports keep working."""

import sys

import msk_core.imu.stream as _moved

sys.modules[__name__] = _moved

"""Moved to msk_core.signal.reps (the tree reads as the data flow); this name stays so existing imports keep working."""

import sys

import msk_core.signal.reps as _moved

sys.modules[__name__] = _moved

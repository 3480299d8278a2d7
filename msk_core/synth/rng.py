"""Deterministic random streams: one independent generator per (seed, purpose) so adding a stream never shifts another."""

from __future__ import annotations

import zlib

import numpy as np


def stream(seed: int, *keys: object) -> np.random.Generator:
    """Generator for ``seed`` and a purpose path (e.g. ``stream(7, "emg", "bench_press", 40.0, "TriLat")``).

    Keys are hashed with CRC-32 (stable across processes, unlike ``hash``)."""
    words = [int(seed) & 0xFFFFFFFF] + [zlib.crc32(repr(k).encode()) for k in keys]
    return np.random.default_rng(np.random.SeedSequence(words))

"""The part of a model pack the estimator uses, as a Protocol (the real packs live in :mod:`msk_core.model`)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import numpy as np

CLAMP_TOLERANCE = np.deg2rad(5.0)  # poses this far outside a pack's fitted range are clamped (and counted)


@runtime_checkable
class PackLike(Protocol):
    """Moment arms and inverse dynamics of a compiled model pack (see ``msk_core.model.ModelPack``)."""

    name: str
    version: str
    coordinates: Sequence[str]
    groups: Sequence[str]
    f_max_ref: np.ndarray

    def moment_arms(self, q: np.ndarray) -> np.ndarray:
        """(n_coordinates, n_groups) moment arms in metres at q (radians)."""
        ...

    def inverse_dynamics(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, hand_load_newton: float) -> np.ndarray:
        """(n_coordinates,) generalised forces in N·m."""
        ...


def resolve_pack(pack: PackLike | str) -> PackLike:
    """A pack object as given, or loaded by name/path through :func:`msk_core.model.load_pack`.

    Packs loaded here use the compiled evaluator: the per-frame loop is where its ~3x faster frames matter (results
    agree with the numpy path to ~1e-13). A pack keeps scratch buffers, so every estimator loads its own.
    """
    if isinstance(pack, str):
        from msk_core.model import Evaluator, load_pack  # lazily: the model package is optional for pure-math use

        return load_pack(pack, evaluator=Evaluator.COMPILED)
    return pack


def fitted_ranges(pack: PackLike) -> tuple[np.ndarray, np.ndarray] | None:
    """(lower, upper) of the pack's fitted coordinate ranges (rad), or None when it declares none."""
    ranges = getattr(pack, "coordinate_ranges", None)
    if ranges is None:
        return None
    r = np.asarray(ranges, dtype=float).reshape(len(pack.coordinates), 2)
    return r[:, 0].copy(), r[:, 1].copy()


def clamp_to_ranges(q: np.ndarray, ranges: tuple[np.ndarray, np.ndarray] | None) -> tuple[np.ndarray, np.ndarray]:
    """The one rule for poses outside a pack's fitted ranges: clamped into them when every coordinate is within
    ``CLAMP_TOLERANCE``, refused further out (never extrapolated). ``q`` is one pose (n_c,) or many (T, n_c); returns
    (q clamped, usable) with ``usable`` a bool per pose (False also for a non-finite pose)."""
    q = np.asarray(q, dtype=float)
    finite = np.all(np.isfinite(q), axis=-1)
    if ranges is None:
        return q, finite
    qc = np.minimum(np.maximum(q, ranges[0]), ranges[1])
    with np.errstate(invalid="ignore"):
        return qc, finite & np.all(np.abs(qc - q) <= CLAMP_TOLERANCE, axis=-1)

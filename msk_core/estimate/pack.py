"""The part of a model pack the estimator uses, as a Protocol (the real packs live in :mod:`msk_core.model`)."""

from __future__ import annotations

from typing import Protocol, Sequence, runtime_checkable

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


def resolve_pack(pack: "PackLike | str") -> PackLike:
    """A pack object as given, or loaded by name/path through :func:`msk_core.model.load_pack`.

    Packs loaded here use the compiled evaluator: the per-frame loop is where its ~3x faster frames matter (results
    agree with the numpy path to ~1e-13). A pack keeps scratch buffers, so every estimator loads its own.
    """
    if isinstance(pack, str):
        from msk_core.model import Evaluator, load_pack  # lazily: the model package is optional for pure-math use

        return load_pack(pack, evaluator=Evaluator.COMPILED)
    return pack


def pack_moment_arms(pack: PackLike, q: np.ndarray) -> np.ndarray:
    """Moment arms at q, clamped into the pack's fitted range by at most CLAMP_TOLERANCE (else NaN)."""
    ranges = getattr(pack, "coordinate_ranges", None)
    if ranges is not None:
        ranges = np.asarray(ranges, dtype=float).reshape(len(q), 2)
        qc = np.minimum(np.maximum(q, ranges[:, 0]), ranges[:, 1])
        if np.any(np.abs(qc - q) > CLAMP_TOLERANCE):
            return np.full((len(pack.coordinates), len(pack.groups)), np.nan)
        q = qc
    return np.asarray(pack.moment_arms(q), dtype=float)

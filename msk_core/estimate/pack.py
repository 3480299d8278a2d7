"""The part of a model pack the estimator uses, as Protocols (the real packs live in :mod:`msk_core.model`).

:class:`PackLike` is what every pack has; what only some packs have is a Protocol of its own, read after an
``isinstance`` check so that mypy checks the reads: :class:`RangedPackLike` (fitted coordinate ranges),
:class:`PosedPackLike` (a reference pose) and :class:`MusclePackLike` (muscle lengths, fibre data, the fused frame).
``msk_core.model.ModelPack`` is all of them; the small packs of the tests and benchmarks are some."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from msk_core.model.names import DisplayNames

CLAMP_TOLERANCE = np.deg2rad(5.0)  # poses this far outside a pack's fitted range are clamped (and counted)


@runtime_checkable
class PackLike(Protocol):
    """What the estimator reads of every model pack: names, reference strengths, moment arms and inverse dynamics
    (``msk_core.model.ModelPack``; tests use smaller ones). Read-only members, so a pack's lists satisfy the
    sequences. A pack may have more, read where present: :class:`RangedPackLike`, :class:`PosedPackLike`,
    :class:`MusclePackLike`."""

    @property
    def name(self) -> str: ...

    @property
    def version(self) -> str: ...

    @property
    def coordinates(self) -> Sequence[str]: ...

    @property
    def groups(self) -> Sequence[str]: ...

    @property
    def f_max_ref(self) -> np.ndarray:
        """(n_groups,) reference maximum isometric forces, N."""
        ...

    def moment_arms(self, q: np.ndarray) -> np.ndarray:
        """(n_coordinates, n_groups) moment arms in metres at q (radians)."""
        ...

    def inverse_dynamics(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, hand_load_newton: float) -> np.ndarray:
        """(n_coordinates,) generalised forces in N·m."""
        ...


@runtime_checkable
class RangedPackLike(PackLike, Protocol):
    """A pack that declares the coordinate ranges its surrogate was fitted over: poses beyond them are clamped or
    refused (:func:`clamp_to_ranges`), and the passive joint effect reads them."""

    @property
    def coordinate_ranges(self) -> np.ndarray:
        """(n_coordinates, 2) fitted (lower, upper) range of each coordinate, rad."""
        ...


@runtime_checkable
class PosedPackLike(PackLike, Protocol):
    """A pack with a reference pose (the pose its model is written around): the estimator's warm-up frame."""

    @property
    def reference_pose(self) -> np.ndarray:
        """(n_coordinates,) reference pose, rad."""
        ...


@runtime_checkable
class MusclePackLike(PackLike, Protocol):
    """A pack with muscle-tendon lengths and fibre data (``ModelPack`` has them): what the muscle-state effects
    (active and passive force-length, force-velocity) and the discrepancy data need; its fused :meth:`frame` gives
    a live frame's lengths, moment arms and torques in one call."""

    @property
    def optimal_fiber_lengths(self) -> np.ndarray:
        """(n_groups,) optimal fibre lengths, m."""
        ...

    @property
    def tendon_slack_lengths(self) -> np.ndarray:
        """(n_groups,) tendon slack lengths, m."""
        ...

    def lengths_and_moment_arms(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """((n_groups,) muscle-tendon lengths in metres, (n_coordinates, n_groups) moment arms) at q, in one call."""
        ...

    def frame(
        self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, hand_load_newton: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """((n_groups,) muscle-tendon lengths, (n_coordinates, n_groups) moment arms, (n_coordinates,) generalised
        forces) at one state, in one call."""
        ...


@runtime_checkable
class NamedPackLike(PackLike, Protocol):
    """A pack with display names for its groups and coordinates (``ModelPack`` has them): what reports show people."""

    @property
    def display_names(self) -> DisplayNames: ...


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
    """(lower, upper) of the pack's fitted coordinate ranges (rad), or None when it declares none
    (not a :class:`RangedPackLike`)."""
    if not isinstance(pack, RangedPackLike):
        return None
    r = np.asarray(pack.coordinate_ranges, dtype=float).reshape(len(pack.coordinates), 2)
    return r[:, 0].copy(), r[:, 1].copy()


def fibre_lengths(pack: PackLike) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(optimal fibre lengths, tendon slack lengths) of a pack with muscle data (:class:`MusclePackLike`), or
    (None, None): the effects that need them say so when evaluated."""
    if not isinstance(pack, MusclePackLike):
        return None, None
    return np.asarray(pack.optimal_fiber_lengths, dtype=float), np.asarray(pack.tendon_slack_lengths, dtype=float)


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

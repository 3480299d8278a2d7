"""Runtime model packs: fast moment arms, muscle-tendon lengths and reduced inverse dynamics (no OpenSim needed).

A pack is one JSON file written by :mod:`msk_core.model.compile`. Poses are validated against the fitted ranges:
by default a pose outside them raises :class:`ModelError`; ``out_of_range=OutOfRange.CLAMP`` evaluates at the
nearest in-range pose instead (use :meth:`ModelPack.in_range` to flag). Nothing is ever extrapolated.
"""

from __future__ import annotations

import enum
import functools
import json
import tomllib
from collections.abc import Mapping, Sequence
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from msk_core.errors import ConfigError, FileFormatError, ModelError
from msk_core.model.names import ROTATION_UNIT, DisplayNames, fallback_names, parse_names
from msk_core.model.poly import FeatureEvaluator, derivative_matrix
from msk_core.model.rigid import RigidModel, compiled_kernels

if TYPE_CHECKING:
    from msk_core.model.kernels import MuscleTables
    from msk_core.model.spec import BalanceSpec, PackSpec

PACK_FORMAT = "msk-model-pack/1"


class OutOfRange(enum.Enum):
    """What moment_arms / mtu_lengths / inverse_dynamics do with a pose outside the fitted ranges."""

    RAISE = "raise"  # ModelError naming the coordinate, value and range
    CLAMP = "clamp"  # evaluate at the pose clamped into the ranges (flag it yourself with in_range)


class Evaluator(enum.Enum):
    """How a pack evaluates a frame. Both agree to ~1e-13 (tests/test_model_reference_eval.py), not bit for bit."""

    NUMPY = "numpy"  # numpy + pinocchio: ~20 numpy calls and 2 pinocchio calls per frame
    COMPILED = "compiled"  # one numba call per frame (msk_core.model.kernels; needs numba, compiled on first use)


class ModelPack:
    """A compiled model pack. Build with :func:`load_pack`."""

    def __init__(self, data: dict, *, path: Path | None = None, evaluator: Evaluator = Evaluator.NUMPY) -> None:
        if data.get("format") != PACK_FORMAT:
            raise FileFormatError(
                f"not a model pack (expected format {PACK_FORMAT!r})",
                path=path,
                field="format",
                value=data.get("format"),
            )
        self.path = path
        self.raw = data
        self._read_description(data, path)
        self._read_length_basis(data)
        self._prepare_numpy()
        self.evaluator = Evaluator(evaluator)
        compiled = self.evaluator is Evaluator.COMPILED
        self.rigid = RigidModel(data["dynamics"], n_coordinates=self._n, compiled=compiled)
        validation = data.get("validation_dynamics")
        self.validation_rigid = (
            RigidModel(validation, n_coordinates=self._n, compiled=compiled) if validation else self.rigid
        )
        self.muscle_tables: MuscleTables | None = None
        if compiled:
            self._prepare_compiled()

    def _read_description(self, data: dict, path: Path | None) -> None:
        """Names, coordinates and their ranges, groups and the muscle parameters."""
        self.name: str = data["name"]
        self.version: str = data["version"]
        self.description: str = data.get("description", "")
        self.coordinates: list[str] = list(data["coordinates"])
        self.coordinate_ranges = np.asarray(data["coordinate_ranges"], dtype=float).reshape(len(self.coordinates), 2)
        self.reference_pose = np.asarray(data["reference_pose"], dtype=float)
        self.coupled: dict[str, dict[str, float]] = data.get("coupled", {})
        self.locked: dict[str, float] = data.get("locked", {})
        self.groups: list[str] = list(data["groups"])
        self.members: dict[str, list[str]] = {g: list(data["members"][g]) for g in self.groups}
        self.member_f_max: dict[str, float] = dict(data["member_f_max"])
        self.f_max_ref = np.asarray(data["f_max_ref"], dtype=float)
        self.optimal_fiber_lengths = np.asarray(data["optimal_fiber_lengths"], dtype=float)
        self.tendon_slack_lengths = np.asarray(data["tendon_slack_lengths"], dtype=float)
        # OpenSim's control bounds per group (StaticOptimization bounds activations by them); packs compiled before
        # they were recorded read as [0, 1]
        self.min_control = np.asarray(data.get("min_control", np.zeros(len(self.groups))), dtype=float)
        self.max_control = np.asarray(data.get("max_control", np.ones(len(self.groups))), dtype=float)
        self.fit_report: dict = data.get("fit_report", {})
        self.display_names: DisplayNames = names_of(data, path)
        self.balance: BalanceSpec = balance_of(data, path)  # the pairs its spec declares for balance metrics

    def _read_length_basis(self, data: dict) -> None:
        """The length surrogates' basis (monomials and hinges) and coefficients, lengths and moment arms stacked."""
        basis = data["basis"]
        self._exponents = np.asarray(basis["exponents"], dtype=np.int64).reshape(-1, len(self.coordinates))
        self._centre = np.asarray(basis["centre"], dtype=float)
        self._half = np.asarray(basis["half_width"], dtype=float)
        self._coef = np.asarray(data["length_coefficients"], dtype=float).reshape(len(self.groups), -1)
        hinges = basis.get("hinges", [])
        self._hinge_var = np.array([int(h[0]) for h in hinges], dtype=np.int64)
        self._hinge_knot = np.array([float(h[1]) for h in hinges], dtype=float)
        self._stacked = _stacked_lengths_and_arms(self._coef, self._exponents, self._hinge_var, self._half)
        self._has_hinges = len(hinges) > 0

    def _prepare_numpy(self) -> None:
        """What the numpy evaluator reuses every call: range limits, power tables, monomial columns."""
        n, g = len(self.coordinates), len(self.groups)
        self._powers = np.arange(int(self._exponents.max(initial=0)) + 1)
        self._lo = self.coordinate_ranges[:, 0].copy()
        self._hi = self.coordinate_ranges[:, 1].copy()
        self._n, self._g = n, g
        self._shape = (n,)
        self._half_range = (self._hi - self._lo) / 2
        # flat index of each monomial factor into the (n, D+1) table of powers: phi = prod(table.flat[index], axis=1)
        flat = np.arange(n)[None, :] * len(self._powers) + self._exponents
        # only the columns of coordinates that appear in some monomial: one take + multiply per coordinate
        self._flat_cols = [np.ascontiguousarray(flat[:, j]) for j in range(n) if self._exponents[:, j].any()]
        if not self._flat_cols:
            self._flat_cols = [np.ascontiguousarray(flat[:, 0])]
        self._hinge_powers = np.array([1.0, 2.0, 3.0])
        self._features = FeatureEvaluator(
            self._exponents, list(zip(self._hinge_var.tolist(), self._hinge_knot.tolist()))
        )
        self._half_range_list = self._half_range.tolist()

    def _prepare_compiled(self) -> None:
        """The compiled evaluator's tables, mode bits and output layout."""
        n, g = self._n, self._g
        kernels = self._kernels = compiled_kernels()
        muscle_tables: MuscleTables = kernels.MuscleTables.build(
            lo=self._lo,
            hi=self._hi,
            centre=self._centre,
            half=self._half,
            half_range=self._half_range,
            reference=self.reference_pose,
            exponents=self._exponents,
            hinge_var=self._hinge_var,
            hinge_knot=self._hinge_knot,
            stacked=self._stacked,
            n_groups=g,
        )
        self.muscle_tables = muscle_tables
        self._frame_kernel = kernels.frame
        self._both = kernels.MUSCLES | kernels.DYNAMICS
        self._modes = {  # (out_of_range, parts) -> kernels.frame mode bits
            (out_of_range, part): (kernels.CLAMP if out_of_range is OutOfRange.CLAMP else 0) | part
            for out_of_range in OutOfRange
            for part in (kernels.MUSCLES, kernels.DYNAMICS, kernels.MUSCLES | kernels.DYNAMICS)
        }
        # the compiled frame's output layout: lengths (G), moment arms (n × G), tau (n), tau per joint (J)
        rigid_tables = self.rigid.compiled_tables
        self._frame_size = g * (n + 1) + n + rigid_tables.n_joints
        self._lengths_at, self._arms_at = slice(0, g), slice(g, g * (n + 1))
        self._tau_at = slice(g * (n + 1), g * (n + 1) + n)
        self._tables = (muscle_tables.ints, muscle_tables.floats, rigid_tables.ints, rigid_tables.floats)

    # ---- poses -------------------------------------------------------------------------------------------------
    def in_range(self, q: np.ndarray) -> np.ndarray:
        """Boolean mask (n_coordinates,): True where q lies inside the fitted range."""
        q = np.asarray(q, dtype=float)
        return (q >= self._lo) & (q <= self._hi)

    def _raise_out_of_range(self, q: np.ndarray) -> None:
        bad = int(np.flatnonzero((q < self._lo) | (q > self._hi))[0])
        raise ModelError(
            f"pack {self.name!r}: {self.coordinates[bad]} = {q[bad]:.4f} rad "
            f"({np.degrees(q[bad]):.1f} deg) outside the fitted range "
            f"[{np.degrees(self._lo[bad]):.1f}, {np.degrees(self._hi[bad]):.1f}] deg "
            "(pass out_of_range=OutOfRange.CLAMP to evaluate at the range limit)"
        )

    def _pose(self, q: np.ndarray, out_of_range: OutOfRange) -> tuple[np.ndarray, np.ndarray]:
        """(q checked or clamped, q - centre): one subtraction serves the range check and the normalisation."""
        q = np.asarray(q, dtype=float)
        if q.shape != self._shape:
            raise ModelError(
                f"pack {self.name!r}: q must have shape ({self._n},) for {self.coordinates}, got {q.shape}"
            )
        if out_of_range is OutOfRange.CLAMP:
            q = np.minimum(np.maximum(q, self._lo), self._hi)
            return q, q - self._centre
        offset = q - self._centre
        # |q - centre| <= half range, on Python floats (cheaper than three numpy calls for a handful of values)
        for value, half in zip(offset.tolist(), self._half_range_list):
            if value > half or -value > half:
                self._raise_out_of_range(q)
        return q, offset

    def _vectors(self, q, qd, qdd) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Contiguous float64 vectors of the pack's n coordinates (the compiled kernels read exactly n values)."""
        q, qd, qdd = (
            np.ascontiguousarray(q, np.float64),
            np.ascontiguousarray(qd, np.float64),
            np.ascontiguousarray(qdd, np.float64),
        )
        shape = self._shape
        if q.shape != shape or qd.shape != shape or qdd.shape != shape:
            bad, value = next((name, a) for name, a in zip(("q", "qd", "qdd"), (q, qd, qdd)) if a.shape != shape)
            raise ModelError(
                f"pack {self.name!r}: {bad} must have shape ({self._n},) for {self.coordinates}, got {value.shape}"
            )
        return q, qd, qdd

    def _compiled(self, q, qd, qdd, hand_load: float, gravity, out_of_range: OutOfRange, dynamics: bool) -> np.ndarray:
        """kernels.frame for muscles only or dynamics only, on checked inputs: a fresh array in its layout."""
        kernels = self._kernels
        if dynamics:
            q, qd, qdd = self._vectors(q, qd, qdd)
            out = np.empty(self._n + self.rigid.compiled_tables.n_joints)
            mode = self._modes[out_of_range, kernels.DYNAMICS]
        else:
            q, qd, qdd = self._vectors(q, q, q)  # qd, qdd not read
            out = np.empty(self._g * (self._n + 1))
            mode = self._modes[out_of_range, kernels.MUSCLES]
        g = self.rigid.gravity if gravity is None else self._gravity(gravity)
        if not self._frame_kernel(q, qd, qdd, float(hand_load), g, mode, *self._tables, out):
            self._raise_out_of_range(q)
        return out

    @staticmethod
    def _gravity(gravity) -> np.ndarray:
        g = np.ascontiguousarray(gravity, dtype=np.float64)
        if g.shape != (3,):
            raise ModelError(f"gravity must be a 3-vector (m/s²), got shape {g.shape}")
        return g

    def _checked(self, q: np.ndarray, out_of_range: OutOfRange) -> np.ndarray:
        return self._pose(q, out_of_range)[0]

    def _evaluate(self, q: np.ndarray) -> np.ndarray:
        """Lengths then moment arms, (g * (n + 1),), at an in-range pose (reference implementation order)."""
        return self._stacked @ self._features((q - self._centre) / self._half)

    def _values(self, q: np.ndarray, out_of_range: OutOfRange) -> tuple[np.ndarray, np.ndarray]:
        q, offset = self._pose(q, out_of_range)
        return q, self._stacked @ self._features(offset / self._half)

    # ---- muscles -----------------------------------------------------------------------------------------------
    def moment_arms(self, q: np.ndarray, *, out_of_range: OutOfRange = OutOfRange.RAISE) -> np.ndarray:
        """Group moment arms (n_coordinates, n_groups) in metres at pose q (rad); r = -dl/dq (OpenSim sign)."""
        return self.lengths_and_moment_arms(q, out_of_range=out_of_range)[1]

    def mtu_lengths(self, q: np.ndarray, *, out_of_range: OutOfRange = OutOfRange.RAISE) -> np.ndarray:
        """Group muscle-tendon lengths (n_groups,) in metres (F_max-weighted mean over the group's bundles)."""
        return self.lengths_and_moment_arms(q, out_of_range=out_of_range)[0]

    def lengths_and_moment_arms(
        self, q: np.ndarray, *, out_of_range: OutOfRange = OutOfRange.RAISE
    ) -> tuple[np.ndarray, np.ndarray]:
        """Both at once (one evaluation): ((n_groups,), (n_coordinates, n_groups))."""
        if self.muscle_tables is None:
            values = self._values(q, out_of_range)[1]
            return values[: self._g], values[self._g :].reshape(self._n, self._g)
        out = self._compiled(q, None, None, 0.0, None, out_of_range, False)
        return out[self._lengths_at], out[self._arms_at].reshape(self._n, self._g)

    def lengths_and_moment_arms_many(
        self, q: np.ndarray, *, out_of_range: OutOfRange = OutOfRange.RAISE
    ) -> tuple[np.ndarray, np.ndarray]:
        """Vectorised over frames (offline work): q (S, n) -> lengths (S, n_groups), moment arms (S, n, n_groups)."""
        q = np.asarray(q, dtype=float)
        if q.ndim != 2 or q.shape[1] != self._n:
            raise ModelError(f"pack {self.name!r}: q must have shape (frames, {self._n}), got {q.shape}")
        if out_of_range is OutOfRange.CLAMP:
            q = np.minimum(np.maximum(q, self._lo), self._hi)
        else:
            bad = np.abs(q - self._centre) > self._half_range
            if bad.any():
                frame = int(np.nonzero(bad)[0][0])
                self._checked(q[frame], OutOfRange.RAISE)  # raises with the coordinate, value and range
        x = (q - self._centre) / self._half
        table = x[:, :, None] ** self._powers[None, None, :]  # (S, n, D+1)
        flat = table.reshape(len(q), -1)
        phi = flat[:, self._flat_cols[0]]
        for col in self._flat_cols[1:]:
            phi = phi * flat[:, col]
        if self._has_hinges:
            d = x[:, self._hinge_var] - self._hinge_knot
            h = np.maximum(d, 0.0)
            hinge = (h[:, :, None] ** self._hinge_powers[None, None, :]).reshape(len(q), -1)
            phi = np.hstack((phi, hinge, (d > 0.0).astype(float)))
        values = phi @ self._stacked.T  # (S, g*(n+1))
        return values[:, : self._g], values[:, self._g :].reshape(len(q), self._n, self._g)

    # ---- dynamics ----------------------------------------------------------------------------------------------
    def inverse_dynamics(
        self,
        q: np.ndarray,
        qd: np.ndarray,
        qdd: np.ndarray,
        hand_load_newton: float = 0.0,
        *,
        gravity: np.ndarray | None = None,
        out_of_range: OutOfRange = OutOfRange.RAISE,
    ) -> np.ndarray:
        """Net joint torques (n_coordinates,) in N·m that produce qdd at (q, qd) while holding the hand load.

        hand_load_newton: total external load (e.g. barbell weight) acting along gravity; the pack's side carries
        its documented share. gravity: optional gravity vector in the model's ground frame (m/s²), e.g. to express a
        tilted root; default the pack's gravity.
        """
        if self.muscle_tables is None:
            q = self._checked(q, out_of_range)
            return self.rigid.inverse_dynamics(q - self.reference_pose, qd, qdd, hand_load_newton, gravity)
        return self._compiled(q, qd, qdd, hand_load_newton, gravity, out_of_range, True)[: self._n]

    def joint_torques(
        self,
        q: np.ndarray,
        qd: np.ndarray,
        qdd: np.ndarray,
        hand_load_newton: float = 0.0,
        *,
        out_of_range: OutOfRange = OutOfRange.RAISE,
    ) -> dict[str, float]:
        """Net moment (N·m) about every joint of the reduced model, by joint name (``"<OpenSim joint>:<coordinate>"``).

        A coupled coordinate's torque is the virtual-work sum over its joints (deadlift: six lumbar levels); this
        gives each level alone, e.g. ``"L5_S1_IVDjnt:L5_S1_FE"`` is the L5/S1 moment literature reports."""
        q = self._checked(q, out_of_range)
        tau = self.rigid.joint_torques(q - self.reference_pose, qd, qdd, hand_load_newton)
        return dict(zip(self.rigid.joint_names, tau.tolist()))

    def frame(
        self,
        q: np.ndarray,
        qd: np.ndarray,
        qdd: np.ndarray,
        hand_load_newton: float = 0.0,
        *,
        out_of_range: OutOfRange = OutOfRange.RAISE,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Everything a live frame needs in one call: (mtu lengths, moment arms, joint torques).

        With ``Evaluator.COMPILED`` one numba call (:mod:`msk_core.model.kernels`), else numpy + pinocchio (the
        baseline ``msk bench model`` shows)."""
        if self.muscle_tables is None:
            return self._frame_numpy(q, qd, qdd, hand_load_newton, out_of_range)
        q, qd, qdd = self._vectors(q, qd, qdd)
        out = np.empty(self._frame_size)
        mode = self._modes[out_of_range, self._both]
        if not self._frame_kernel(q, qd, qdd, float(hand_load_newton), self.rigid.gravity, mode, *self._tables, out):
            self._raise_out_of_range(q)
        return out[self._lengths_at], out[self._arms_at].reshape(self._n, self._g), out[self._tau_at]

    def _frame_numpy(
        self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, hand_load_newton: float, out_of_range: OutOfRange
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        q, values = self._values(q, out_of_range)
        tau = self.rigid.inverse_dynamics_numpy(q - self.reference_pose, qd, qdd, hand_load_newton, None)
        return values[: self._g], values[self._g :].reshape(self._n, self._g), tau

    def info(self) -> dict:
        """Summary for printing."""
        return {
            "name": self.name,
            "version": self.version,
            "coordinates": self.coordinates,
            "ranges_deg": np.degrees(self.coordinate_ranges).round(1).tolist(),
            "groups": {g: self.members[g] for g in self.groups},
        }


def _stacked_lengths_and_arms(
    coef: np.ndarray, exponents: np.ndarray, hinge_var: np.ndarray, half: np.ndarray
) -> np.ndarray:
    """Group lengths, then moment arms r = -dl/dq per coordinate, as one matrix over the feature vector
    [monomials (M), h1, h1², h1³, h2, ... (3H), step1 .. stepH (H)] (lengths use M + 3H): (g*(n+1), M + 4H)."""
    g, n = coef.shape[0], exponents.shape[1]
    n_mono, n_h = len(exponents), len(hinge_var)
    poly, hcoef = coef[:, :n_mono], coef[:, n_mono:]
    lengths = np.zeros((g, n_mono + 4 * n_h))
    lengths[:, :n_mono] = poly
    lengths[:, n_mono : n_mono + 3 * n_h] = hcoef
    rows = [lengths]
    for j in range(n):
        r = np.zeros((g, n_mono + 4 * n_h))
        r[:, :n_mono] = poly @ derivative_matrix(exponents, j)
        for i in range(n_h):
            if hinge_var[i] != j:
                continue
            a1, a2, a3 = hcoef[:, 3 * i], hcoef[:, 3 * i + 1], hcoef[:, 3 * i + 2]
            r[:, n_mono + 3 * n_h + i] += a1  # d h / dx = step
            r[:, n_mono + 3 * i] += 2 * a2  # d h² / dx = 2h
            r[:, n_mono + 3 * i + 1] += 3 * a3  # d h³ / dx = 3h²
        rows.append(-r / half[j])
    return np.ascontiguousarray(np.vstack(rows))


def _packs_dir():
    return resources.files("msk_core.model") / "packs"


def available_packs() -> list[str]:
    """Names of the packs shipped with msk_core."""
    return sorted(p.name[: -len(".json")] for p in _packs_dir().iterdir() if p.name.endswith(".json"))


def is_known_exercise(exercise: str, also: tuple[str, ...] = ()) -> bool:
    """Whether ``exercise`` names a shipped pack (or one of ``also``, e.g. the pack a node was started with): what
    a load event may say is under way. Bytes that happen to decode as a load event name something else."""
    return exercise in also or exercise in available_packs()


def _read_pack(name_or_path: str | Path) -> tuple[dict, Path]:
    """The JSON of a shipped pack (by name) or of a pack file (by path), and where it was read."""
    candidate = Path(name_or_path)
    if candidate.suffix == ".json" or candidate.is_file():
        path = candidate
        try:
            text = path.read_text()
        except OSError as exc:
            raise FileFormatError(f"cannot read model pack: {exc.strerror}", path=path) from exc
    else:
        resource = _packs_dir() / f"{name_or_path}.json"
        if not resource.is_file():
            raise ModelError(f"no shipped model pack {str(name_or_path)!r}; available: {', '.join(available_packs())}")
        path = Path(str(resource))
        text = resource.read_text()
    try:
        return json.loads(text), path
    except json.JSONDecodeError as exc:
        raise FileFormatError(f"not valid JSON: {exc.msg}", path=path, line=exc.lineno) from exc


def load_pack(name_or_path: str | Path, *, evaluator: Evaluator = Evaluator.NUMPY) -> ModelPack:
    """Load a shipped pack by name (e.g. ``"arm26"``) or a pack JSON file by path.

    evaluator: ``Evaluator.COMPILED`` for the fast per-frame path (numba; ~3x faster frames, compiled once and
    cached on first use); ``Evaluator.NUMPY`` (default) keeps the numpy + pinocchio arithmetic."""
    data, path = _read_pack(name_or_path)
    return ModelPack(data, path=path, evaluator=evaluator)


def _spec_table(data: dict, table: str, path: Path | None) -> object:
    """Table ``table`` of the spec embedded in pack ``data`` (``{}`` when it has none)."""
    try:
        return tomllib.loads(data.get("spec", "")).get(table, {})
    except tomllib.TOMLDecodeError as exc:
        raise FileFormatError(f"the pack's embedded spec is not valid TOML: {exc}", path=path, field="spec") from exc


def balance_of(data: dict, path: Path | None = None) -> BalanceSpec:
    """The pairs a pack declares for balance metrics: its embedded spec's ``[balance]`` table
    (:func:`msk_core.model.spec.parse_balance`), checked against its groups and coordinates; none without one."""
    from msk_core.model.spec import parse_balance

    table = _spec_table(data, "balance", path)
    return parse_balance(table, list(data["groups"]), list(data["coordinates"]), path=path, text=data.get("spec", ""))


def names_of(data: dict, path: Path | None = None) -> DisplayNames:
    """The display names of a pack's groups and coordinates: its spec's ``[names]`` table (msk_core.model.names),
    the model names where it gives none. The spec the pack was compiled from is embedded in the pack (``spec``)."""
    table = _spec_table(data, "names", path)
    groups, coordinates = list(data["groups"]), list(data["coordinates"])
    names = parse_names(table, [*groups, *coordinates], path=path, text=data.get("spec", ""))
    return DisplayNames.of(groups, {c: ROTATION_UNIT for c in coordinates}, names)  # pack coordinates: rotations


@functools.lru_cache(maxsize=32)
def pack_display_names(name_or_path: str | Path) -> DisplayNames:
    """:func:`names_of` a shipped pack or a pack file without building the pack (what a view or page needs)."""
    return names_of(*_read_pack(name_or_path))


def names_for(exercise: str, groups: Sequence[str] = (), overrides: Mapping[str, str] | None = None) -> DisplayNames:
    """The display names a surface shows for frames of ``exercise`` (a shipped pack's name) with ``groups``: the
    pack's names with a session's ``overrides`` (``LoadEvent.names``) in place; the model names when the exercise
    names no shipped pack or the groups are not all the pack's (frames of another pack)."""
    try:
        names = pack_display_names(exercise) if exercise in available_packs() else None
    except (ModelError, FileFormatError, ConfigError):  # a broken pack file: its frames still show, by model name
        names = None
    if names is None or not set(groups) <= set(names.groups):
        names = fallback_names(groups)
    return names.with_overrides(overrides or {})


#: Spec tables that declare things about a pack without entering its fit: changing them needs no recompile.
DECLARATIVE_TABLES = ("names", "balance")


def with_names(data: dict, spec: PackSpec) -> dict:
    """A copy of pack ``data`` carrying ``spec`` as its embedded spec, when the two differ only in their
    :data:`DECLARATIVE_TABLES` (``[names]``, ``[balance]``) and comments: a change of display names or balance pairs
    needs no recompile. Any other difference is refused, naming the spec file and the first differing key."""
    old, new = tomllib.loads(data.get("spec", "")), tomllib.loads(spec.text)
    for table in DECLARATIVE_TABLES:
        old.pop(table, None)
        new.pop(table, None)
    changed = sorted(k for k in old.keys() | new.keys() if old.get(k) != new.get(k))
    if changed:
        raise ModelError(
            f"{spec.path or 'the spec'}: differs from the spec pack {data.get('name')!r} was compiled "
            f"from in [{changed[0]}], not only in [names]: recompile the pack (msk model compile; a change of "
            f"[{'] or ['.join(DECLARATIVE_TABLES)}] alone needs none)"
        )
    out = dict(data, spec=spec.text)
    names_of(out)  # the names fit the pack's groups and coordinates
    balance_of(out)  # and so do the balance pairs
    return out

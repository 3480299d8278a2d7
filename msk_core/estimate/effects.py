"""Model effects beyond F = F_max * a, as the subject profile's ``effects`` section carries them into estimation.

Found and fitted by :mod:`msk_core.discrepancy` (``msk discrepancy``); used by :class:`FrameEstimator` so that
``msk estimate``, ``msk evaluate``, the live estimator node and the demo pick them up through the profile. Each effect
enters the per-frame QP without changing it (see docs/discrepancy.md for the formulas):

- per-frame force scales (``fl_active``, ``fv``; ``moment_arm_scale`` per group and coordinate; the strength re-fit
  ``strength_gain``): the moment-arm matrix is scaled column by column, R~ = R * s(q, qd);
- known torque offsets (``fl_passive``, ``passive_joint``, ``damping``, ``load_misreport``): the torque the active
  muscles must produce is tau - offset(q, qd, load);
- time shifts (``emd``): the prior is looked up at the phase ``delay`` seconds ago (frame history kept here);
- EMG unmixing (``crosstalk``): the prior's means of the measured groups are unmixed once, at construction
  (incoherent sources: powers add, :func:`unmix_envelopes`).

Sign conventions: inverse-dynamics torque = active muscle torque + passive/offset terms; a lengthening velocity is
negative shortening; moment arm r = -dL/dq, so dL/dt = -R^T qd.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from enum import StrEnum

import numpy as np

from msk_core.errors import EstimationError
from msk_core.estimate.pack import MusclePackLike, PackLike, fitted_ranges

EFFECTS_FORMAT_VERSION = 1


class Effect(StrEnum):
    """Every effect a profile may carry and the discrepancy workflow may name. The synthetic generator's hidden
    effects (:class:`msk_core.synth.effects.Effects`) use the same names for the same physics."""

    EMD = "emd"
    FL_ACTIVE = "fl_active"
    FL_PASSIVE = "fl_passive"
    PASSIVE_JOINT = "passive_joint"
    FV = "fv"
    DAMPING = "damping"
    # the bar's true load differs from the reported (logged) one; parameter ``true_over_reported`` = true / reported
    # (the generator's ``load_misreport`` setting is the inverse, reported / true)
    LOAD_MISREPORT = "load_misreport"
    MOMENT_ARM_SCALE = "moment_arm_scale"
    CROSSTALK = "crosstalk"


#: names profiles were written with before an effect was renamed -> the effect (read, never written)
FORMER_EFFECT_NAMES = {"load_scale": Effect.LOAD_MISREPORT}
#: every effect name the profile may carry
EFFECT_NAMES = tuple(e.value for e in Effect)
MUSCLE_STATE_EFFECTS = (Effect.FL_ACTIVE, Effect.FL_PASSIVE, Effect.FV)
PASSIVE_SHAPE = 4.0  # exponential shape of the passive force-length curve (Thelen 2003: k^PE = 4)
FV_CURVATURE = 0.25  # Hill's a/F0 (shortening branch)
FV_ECCENTRIC_HALF = 0.17  # eccentric plateau reached half-way at this lengthening speed (fraction of v_max)


def effect_named(name: object, where: str) -> Effect:
    """The :class:`Effect` called ``name`` in a file or setting (a former name too); :class:`EstimationError` naming
    ``where`` and the known names otherwise. The one place names are read."""
    if isinstance(name, str):
        if name in FORMER_EFFECT_NAMES:
            return FORMER_EFFECT_NAMES[name]
        if name in EFFECT_NAMES:
            return Effect(name)
    raise EstimationError(f"{where}: unknown effect {name!r}; known: {', '.join(EFFECT_NAMES)}")


class Nuisance(StrEnum):
    """The discrepancy model's coefficients that belong to no effect (docs/discrepancy.md, "Model")."""

    GAIN = "gain"  # a measured group's strength re-fit (per group)
    PRIOR = "prior"  # an unmeasured group's prior-mean scale (per group)
    DEMAND = "demand"  # an unmeasured group's share of the frame's demand in one phase bin (per group and bin)
    OFFSET = "offset"  # a coordinate's torque offset (per coordinate)


@dataclass(frozen=True)
class CoefKey:
    """One linear coefficient of the discrepancy model or a calibration's torque basis: what it belongs to, which of
    its parameters, and for which group / phase bin / coordinate. ``str()`` is the one written form (reports, the
    calibration's ``torque_basis`` table): the non-empty parts joined by ":", e.g. ``damping:b:elbow_flexion``."""

    term: Effect | Nuisance
    parameter: str = ""  # the effect's parameter ("scale", "k_lower", "k_upper", "b"); "" for a nuisance term
    group: str = ""
    phase_bin: int | None = None
    coordinate: str = ""

    def __str__(self) -> str:
        bin_ = "" if self.phase_bin is None else str(self.phase_bin)
        return ":".join(x for x in (self.term.value, self.parameter, self.group, bin_, self.coordinate) if x)


# The model's muscle curves. The synthetic generator (msk_core.synth.effects) has its own on purpose: its are the
# simulated subject's truth (Thelen's constants, fibres held to [0.4, 1.8] l_opt), these the model msk discrepancy
# fits to it (width, strain, v_max and eccentric plateau free; the [0.3, 2.0] clip only a numerical guard, which the
# demo sessions never reach). Shared, a change of the model would move the truth with it and the discrepancy tests
# would test the model against itself; msk_core.synth.effects gives the numbers where the two differ.


def fibre_length(lengths: np.ndarray, optimal: np.ndarray, slack: np.ndarray) -> np.ndarray:
    """Normalised fibre length, rigid tendon, no pennation: (L_mtu - L_slack) / L_opt, clipped to [0.3, 2.0] (a
    numerical guard, not the generator's [0.4, 1.8]: see above)."""
    return np.clip((np.asarray(lengths) - slack) / optimal, 0.3, 2.0)


def _needed(value: np.ndarray | None, what: str, effect: Effect) -> np.ndarray:
    """``value``, without which ``effect`` cannot be evaluated (:class:`EstimationError` naming both when missing)."""
    if value is None:
        raise EstimationError(f"effect {effect} needs the {what}, which were not given (a pack without them?)")
    return value


def _fibre_length_for(
    effect: Effect, lengths: np.ndarray | None, optimal: np.ndarray | None, slack: np.ndarray | None
) -> np.ndarray:
    """:func:`fibre_length` for ``effect``, which needs the muscle lengths and the pack's fibre data."""
    return fibre_length(
        _needed(lengths, "muscle-tendon lengths", effect),
        _needed(optimal, "optimal fibre lengths", effect),
        _needed(slack, "tendon slack lengths", effect),
    )


def shortening_speed(arms: np.ndarray, qd: np.ndarray, optimal: np.ndarray, v_max: float) -> np.ndarray:
    """Shortening speed in units of v_max (optimal fibre lengths per second); arms (..., n_c, G), qd (..., n_c)."""
    lengthening = -np.einsum("...ng,...n->...g", arms, qd)  # dL/dt = -R^T qd
    return -lengthening / (v_max * optimal)


def active_force_length(l_norm: np.ndarray, width: float) -> np.ndarray:
    """Gaussian active force-length curve exp(-((l - 1) / width)^2)."""
    return np.exp(-(((l_norm - 1.0) / width) ** 2))


def passive_force_length(l_norm: np.ndarray, strain: float) -> np.ndarray:
    """Passive force / F_max: (exp(k (l - 1) / strain) - 1) / (exp(k) - 1) beyond optimal length (1 at l = 1 + strain)."""
    stretch = np.maximum(l_norm - 1.0, 0.0)
    return np.expm1(PASSIVE_SHAPE * stretch / strain) / np.expm1(PASSIVE_SHAPE)


def force_velocity(v: np.ndarray, eccentric: float) -> np.ndarray:
    """Hill force-velocity multiplier; v = shortening speed / v_max (negative: lengthening, plateau ``eccentric``)."""
    v = np.asarray(v, dtype=float)
    shortening = np.maximum(1.0 - v, 0.0) / (1.0 + np.maximum(v, 0.0) / FV_CURVATURE)
    u = np.maximum(-v, 0.0)
    lengthening = 1.0 + (eccentric - 1.0) * u / (u + FV_ECCENTRIC_HALF)
    return np.where(v >= 0.0, shortening, lengthening)


def force_factor(
    lengths: np.ndarray | None,
    arms: np.ndarray,
    qd: np.ndarray,
    optimal: np.ndarray | None,
    slack: np.ndarray | None,
    effects: Mapping[Effect, dict | None],
) -> np.ndarray:
    """The one force factor: on each group's active force, active force-length x force-velocity, for one frame ((G,);
    arms (n_c, G), qd (n_c,)) or many ((T, G)). ``effects``: the parameters of those on, FL_ACTIVE {"width"} and FV
    {"v_max", "eccentric"} (any other effect is not a force factor; None is off); 1 where neither is on. The live
    estimator (:meth:`EffectsProfile.force_scale`), the discrepancy fit and the re-calibration all take it from here."""
    scale = np.ones(arms.shape[:-2] + arms.shape[-1:])
    fl_active, fv = effects.get(Effect.FL_ACTIVE), effects.get(Effect.FV)
    if fl_active:
        scale = active_force_length(_fibre_length_for(Effect.FL_ACTIVE, lengths, optimal, slack), fl_active["width"])
    if fv:
        speed = shortening_speed(arms, qd, _needed(optimal, "optimal fibre lengths", Effect.FV), fv["v_max"])
        scale = scale * force_velocity(speed, fv["eccentric"])
    return scale


def passive_joint_basis(q: np.ndarray, lo: np.ndarray, hi: np.ndarray, decay: float) -> tuple[np.ndarray, np.ndarray]:
    """(toward upper limit, toward lower limit) exponentials exp((q - hi)/decay), exp((lo - q)/decay); each 1 at its
    range limit. The joint's passive elastic moment is k_lo * lower - k_hi * upper (it pushes away from the limit)."""
    return np.exp((q - hi) / decay), np.exp((lo - q) / decay)


#: the effects that are torque linear in coefficients
TORQUE_TERMS = (Effect.FL_PASSIVE, Effect.PASSIVE_JOINT, Effect.DAMPING)


def torque_term_names(model: dict[Effect, dict], coordinates: list[str]) -> list[CoefKey]:
    """The keys of :func:`torque_term_columns`' coefficients, in order."""
    names = [CoefKey(Effect.FL_PASSIVE, "scale")] if Effect.FL_PASSIVE in model else []
    if Effect.PASSIVE_JOINT in model:
        for c in coordinates:
            names += [
                CoefKey(Effect.PASSIVE_JOINT, "k_lower", coordinate=c),
                CoefKey(Effect.PASSIVE_JOINT, "k_upper", coordinate=c),
            ]
    if Effect.DAMPING in model:
        names += [CoefKey(Effect.DAMPING, "b", coordinate=c) for c in coordinates]
    return names


def torque_term_columns(
    model: dict[Effect, dict],
    q: np.ndarray,
    qd: np.ndarray,
    lengths: np.ndarray | None,
    arms: np.ndarray | None,
    f_max: np.ndarray,
    optimal: np.ndarray | None,
    slack: np.ndarray | None,
    lo: np.ndarray | None,
    hi: np.ndarray | None,
) -> np.ndarray:
    """(..., n_c, p) the torque terms of ``model`` (its ``TORQUE_TERMS``, each with its nonlinear setting) per unit
    coefficient, N·m: passive muscle force Σ_g R_g F_max,g p_g(l) (one scale); the joint's elastic moment at each range
    limit (k_lower, k_upper per coordinate); damping −q̇ (b per coordinate). Every coefficient is >= 0 physically.
    q, qd (..., n_c); lengths (..., G) and arms (..., n_c, G). The one definition the discrepancy model, the
    re-calibration and the estimator's torque offset share."""
    n_c = q.shape[-1]
    eye = np.eye(n_c)
    cols = []
    if Effect.FL_PASSIVE in model:
        pas = passive_force_length(
            _fibre_length_for(Effect.FL_PASSIVE, lengths, optimal, slack), model[Effect.FL_PASSIVE]["strain"]
        )
        cols.append(np.einsum("...ng,...g->...n", _needed(arms, "moment arms", Effect.FL_PASSIVE), f_max * pas))
    if Effect.PASSIVE_JOINT in model:
        up, low = passive_joint_basis(
            q,
            _needed(lo, "coordinate ranges", Effect.PASSIVE_JOINT),
            _needed(hi, "coordinate ranges", Effect.PASSIVE_JOINT),
            model[Effect.PASSIVE_JOINT]["decay_rad"],
        )
        for c in range(n_c):
            cols += [low * eye[c], -up * eye[c]]
    if Effect.DAMPING in model:
        cols += [-qd * eye[c] for c in range(n_c)]
    return np.stack(cols, axis=-1) if cols else np.zeros(np.shape(q) + (0,))


def crosstalk_matrix(n: int, fraction: float) -> np.ndarray:
    """Electrode k sees (1 - c) of its muscle and c shared by its neighbours k - 1, k + 1 in the electrode order."""
    m = np.eye(n) * (1.0 - fraction)
    for k in range(n):
        nb = [j for j in (k - 1, k + 1) if 0 <= j < n]
        for j in nb:
            m[k, j] = fraction / len(nb)
    if n == 1:
        m[0, 0] = 1.0
    return m


def unmix_envelopes(e: np.ndarray, fraction: float) -> np.ndarray:
    """Envelopes (..., n) in electrode order with the neighbours' cross-talk removed. Cross-talk mixes the raw signals
    of different muscles, which are incoherent: powers add, so envelope^2 = (M o M) s^2 (o: element-wise), and
    s = sqrt(max((M o M)^-1 e^2, 0))."""
    m = crosstalk_matrix(e.shape[-1], fraction)
    inv = np.linalg.inv(m * m)
    return np.sqrt(np.clip((np.asarray(e) ** 2) @ inv.T, 0.0, None))


@dataclass
class ModelEffects:
    """The profile's effects, ready for per-frame use. ``from_dict`` checks names, versions and the pack."""

    effects: list[dict]  # [{"name": Effect, "parameters": {...}}] (from_dict reads the names)
    groups: list[str]
    coordinates: list[str]
    strength_gain: np.ndarray  # (G,) multiplies F_max (the re-fit that goes with the effects; 1 = unchanged)
    evidence: dict = field(default_factory=dict)
    # derived, per pack
    _arm_scale: np.ndarray | None = None
    _optimal: np.ndarray | None = None
    _slack: np.ndarray | None = None
    _lo: np.ndarray | None = None
    _hi: np.ndarray | None = None

    @property
    def names(self) -> list[Effect]:
        return [e["name"] for e in self.effects]

    def params(self, effect: Effect) -> dict | None:
        for e in self.effects:
            if e["name"] == effect:
                return e["parameters"]
        return None

    @property
    def needs_lengths(self) -> bool:
        return any(n in self.names for n in MUSCLE_STATE_EFFECTS)

    @property
    def delay_frames(self) -> int:
        p = self.params(Effect.EMD)
        if not p or p["delay_s"] <= 0:
            return 0
        return int(round(p["delay_s"] / p["frame_interval_s"]))

    @property
    def load_ratio(self) -> float:
        """true / reported external load (1 without ``load_misreport``)."""
        p = self.params(Effect.LOAD_MISREPORT)
        return 1.0 if p is None else float(p["true_over_reported"])

    # -- (de)serialisation -------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "format_version": EFFECTS_FORMAT_VERSION,
            "effects": self.effects,
            "strength_gain": {g: round(float(k), 6) for g, k in zip(self.groups, self.strength_gain)},
            "evidence": self.evidence,
        }

    @classmethod
    def from_dict(cls, data: dict, groups: list[str], coordinates: list[str]) -> ModelEffects:
        if not isinstance(data, dict):
            raise EstimationError("effects: must be a table")
        version = data.get("format_version")
        if version != EFFECTS_FORMAT_VERSION:
            raise EstimationError(
                f"effects.format_version: {version!r} is not supported (this software reads {EFFECTS_FORMAT_VERSION})"
            )
        effects = []
        for e in data.get("effects", []):
            if not isinstance(e, dict) or not isinstance(e.get("parameters"), dict):
                raise EstimationError(f"effects.effects: malformed effect {e!r} (a table with name and parameters)")
            effects.append({**e, "name": effect_named(e.get("name"), "effects.effects")})
        gains = data.get("strength_gain", {})
        unknown = sorted(set(gains) - set(groups))
        if unknown:
            raise EstimationError(f"effects.strength_gain: groups {unknown} are not in the profile's groups")
        gain = np.array([float(gains.get(g, 1.0)) for g in groups])
        if not np.all(gain > 0):
            raise EstimationError(f"effects.strength_gain: gains must be positive, got {gain}")
        return cls(effects, list(groups), list(coordinates), gain, dict(data.get("evidence", {})))

    def bind(self, pack: PackLike) -> ModelEffects:
        """Pack-dependent constants (fibre lengths, ranges, the moment-arm scale matrix)."""
        out = replace(self)
        if self.needs_lengths:
            if not isinstance(pack, MusclePackLike):
                raise EstimationError(f"effects {self.names} need muscle lengths, which pack {pack.name!r} lacks")
            out._optimal = np.asarray(pack.optimal_fiber_lengths, dtype=float)
            out._slack = np.asarray(pack.tendon_slack_lengths, dtype=float)
        if Effect.PASSIVE_JOINT in self.names:
            ranges = fitted_ranges(pack)
            if ranges is None:
                raise EstimationError(
                    f"effect passive_joint needs the coordinate ranges, which pack {pack.name!r} lacks"
                )
            out._lo, out._hi = ranges
        scale = np.ones((len(self.coordinates), len(self.groups)))
        p = self.params(Effect.MOMENT_ARM_SCALE)
        if p:
            for g, per in p["scales"].items():
                for c, s in per.items():
                    if g not in self.groups or c not in self.coordinates:
                        raise EstimationError(f"effects moment_arm_scale: unknown group/coordinate {g!r}/{c!r}")
                    scale[self.coordinates.index(c), self.groups.index(g)] = float(s)
        out._arm_scale = scale if p else None
        return out

    # -- per frame ---------------------------------------------------------------------------------------------
    def force_scale(self, lengths: np.ndarray | None, arms: np.ndarray, qd: np.ndarray) -> np.ndarray | None:
        """(G,) per-frame multiplier of each group's active force (:func:`force_factor`), None when no such effect is
        on (the estimator then leaves the forces as they are)."""
        effects = {e: self.params(e) for e in (Effect.FL_ACTIVE, Effect.FV)}
        if not any(effects.values()):
            return None
        return force_factor(lengths, arms, qd, self._optimal, self._slack, effects)

    def torque_offset(self, q, qd, lengths, arms, f_max_profile) -> np.ndarray | None:
        """Torque not produced by the active muscles (N·m, per coordinate): passive muscle, passive joint, damping
        (:func:`torque_term_columns` times the fitted coefficients; ID = muscle - b qd: the muscles also overcome the
        damping). None when the profile has none of them."""
        model: dict[Effect, dict] = {}
        for name in TORQUE_TERMS:
            params = self.params(name)
            if params:
                model[name] = params
        if not model:
            return None
        coef = [model[Effect.FL_PASSIVE]["scale"]] if Effect.FL_PASSIVE in model else []
        if Effect.PASSIVE_JOINT in model:
            p = model[Effect.PASSIVE_JOINT]
            coef += [x for pair in zip(p["k_lower_nm"], p["k_upper_nm"]) for x in pair]
        if Effect.DAMPING in model:
            coef += list(model[Effect.DAMPING]["b_nms_per_rad"])
        cols = torque_term_columns(
            model,
            np.asarray(q, dtype=float),
            np.asarray(qd, dtype=float),
            lengths,
            arms,
            f_max_profile,
            self._optimal,
            self._slack,
            self._lo,
            self._hi,
        )
        return cols @ np.asarray(coef, dtype=float)

    def new_phase_history(self) -> deque | None:
        n = self.delay_frames
        return deque(maxlen=n + 1) if n > 0 else None

    def unmix_prior(self, prior):
        """The prior with the measured groups' means unmixed (``crosstalk``); as given otherwise."""
        p = self.params(Effect.CROSSTALK)
        if not p or prior is None:
            return prior
        order = [g for g in p["electrode_order"] if g in self.groups]
        idx = [self.groups.index(g) for g in order]
        mean = prior.mean.copy()
        mean[:, idx] = np.clip(unmix_envelopes(mean[:, idx], p["fraction"]), 0.0, 1.0)
        rest = None if prior.rest_mean is None else prior.rest_mean.copy()
        if rest is not None:
            rest[idx] = np.clip(unmix_envelopes(rest[idx], p["fraction"]), 0.0, 1.0)
        return replace(prior, mean=mean, rest_mean=rest)

"""Re-calibration with a candidate's torque in the calibration (docs/discrepancy.md, "Re-calibration").

A calibration on trials that carry a moment the activations do not produce (a passive elastic moment, joint damping)
takes it into the strengths: a passive extension moment raises the extensors' and lowers the flexors' F_max. The
discrepancy model's strength re-fit is held near the calibrated strengths (model.STRENGTH_GAIN_RANGE), so it cannot
undo that, and the candidate that describes the moment then explains only what is left of it. For the candidates that
are torque terms (``TORQUE_EFFECTS``), the calibration is therefore re-run with the candidate's torque as a basis whose
coefficients it fits with the strengths (``CalibrationFrames.torque_basis``), and the candidate is fitted and scored
with those strengths, against the model without it re-calibrated the same way (same trials, settings and delay).
The force-factor candidates (``FORCE_EFFECTS``: active force-length, force-velocity) are re-calibrated the same way,
with their factor on each frame's moment arms: otherwise the candidates that describe a moment would get a freedom
the candidates that describe a force do not, and win against them for that alone.
"""

from __future__ import annotations

import dataclasses
import json
from typing import TYPE_CHECKING

import numpy as np

from msk_core.estimate.calibrate import CalibrationResult, CalibrationSettings
from msk_core.estimate.effects import TORQUE_TERMS, Effect, force_factor, torque_term_columns, torque_term_names
from msk_core.estimate.pack import PackLike, fibre_lengths, fitted_ranges
from msk_core.estimate.profile import SubjectProfile
from msk_core.estimate.trial import TrialData

if TYPE_CHECKING:  # imported where used (msk_core.estimate.pipeline imports more than this module needs at load)
    from msk_core.estimate.pipeline import CalibrationInputs

TORQUE_EFFECTS = TORQUE_TERMS  # re-calibrated with their torque as a basis
FORCE_EFFECTS = (Effect.FL_ACTIVE, Effect.FV)  # ... with their per-frame force factor on the moment arms
RECALIBRATED = TORQUE_EFFECTS + FORCE_EFFECTS  # the candidates fitted with a re-calibration (muscle and joint state)
# the effects a re-calibration can carry: those, and the delay as the calibration's own EMG delay; a model with any
# other (cross-talk, load scale, moment-arm scales) is not re-calibrated
HONOURED = RECALIBRATED + (Effect.EMD,)
# L-BFGS-B's relative-reduction stop for a re-calibration: it compares models by the strengths it returns, which at
# 1e-12 differ from the profile's 1e-15 solve by ~2e-5 (relative) and take ~40 % fewer iterations (docs, Re-calibration)
RECALIBRATION_FTOL = 1e-12


def calibration_settings(profile: SubjectProfile) -> CalibrationSettings:
    """The settings the profile was calibrated with (its report's ``settings``); the defaults where absent."""
    stored = ((profile.calibration or {}).get("settings")) or {}
    known = {f.name for f in dataclasses.fields(CalibrationSettings)}
    kwargs = {k: v for k, v in stored.items() if k in known} if isinstance(stored, dict) else {}
    if isinstance(kwargs.get("strength_bounds"), list):
        kwargs["strength_bounds"] = tuple(kwargs["strength_bounds"])
    try:
        return CalibrationSettings(**kwargs)
    except (TypeError, ValueError):
        return CalibrationSettings()


def torque_columns(pack: PackLike, trial: TrialData, model: dict[Effect, dict], f_max: np.ndarray) -> np.ndarray:
    """(T, n_c, p) the torque terms of ``model`` on every frame of ``trial``, N·m per unit coefficient
    (effects.torque_term_columns, as the discrepancy model writes them; names: effects.torque_term_names), with the
    profile's F_max."""
    q = np.nan_to_num(trial.q)
    lengths = arms = None
    if Effect.FL_PASSIVE in model:
        mech = trial.mechanics(pack)
        lengths, arms = mech.lengths, mech.moment_arms
    lo, hi = fitted_ranges(pack) or (None, None)
    return torque_term_columns(
        model,
        q,
        np.nan_to_num(trial.qd),
        lengths,
        arms,
        f_max,
        *fibre_lengths(pack),
        lo,
        hi,
    )


class Recalibrator:
    """Calibrations of the training trials with a model's torque terms in them (cached per model)."""

    def __init__(self, pack: PackLike, profile: SubjectProfile, train: list[TrialData], base_delay_s: float) -> None:
        self.pack, self.train = pack, list(train)
        settings = calibration_settings(profile)
        self.settings = dataclasses.replace(settings, ftol=max(settings.ftol, RECALIBRATION_FTOL))
        self.base_delay_s = base_delay_s
        self.f_max_profile = np.asarray(profile.f_max, dtype=float)
        self.reports: dict[str, dict] = {}  # by json.dumps(model, sort_keys=True)
        self._cache: dict[str, np.ndarray] = {}
        self._plain: dict[float, CalibrationResult] = {}  # delay -> the calibration without a torque basis (warm start)
        self._inputs: dict[float, CalibrationInputs] = {}  # delay -> the shifted trials, prior, min-effort error

    @staticmethod
    def supports(model: dict[Effect, dict]) -> bool:
        return all(name in HONOURED for name in model)

    def f_max(self, model: dict[Effect, dict]) -> np.ndarray:
        """The strengths of a calibration with ``model``'s torque terms fitted alongside (its delay applied to the
        EMG); ``{}``: the plain calibration of these trials with the profile's settings."""
        from msk_core.estimate.pipeline import TorqueBasis, calibrate_inputs, calibration_inputs

        if not self.supports(model):
            raise ValueError(f"a re-calibration cannot carry {sorted(set(model) - set(HONOURED))}")
        key = json.dumps(model, sort_keys=True)
        if key not in self._cache:
            terms = {k: v for k, v in model.items() if k in TORQUE_EFFECTS}
            forces = {k: v for k, v in model.items() if k in FORCE_EFFECTS}
            scale = (lambda t: self._force_scale(t, forces)) if forces else None
            basis = None
            if terms:
                names = torque_term_names(terms, list(self.pack.coordinates))
                basis = TorqueBasis(
                    columns=lambda t: torque_columns(self.pack, t, terms, self.f_max_profile),
                    lower=np.zeros(len(names)),
                    names=tuple(str(k) for k in names),  # the calibration report's table is keyed by text
                )
            delay = float(model.get(Effect.EMD, {}).get("delay_total_s", self.base_delay_s))
            plain = basis is None and scale is None
            if not plain and delay not in self._plain:
                self.f_max({k: v for k, v in model.items() if k not in RECALIBRATED})
            if delay not in self._inputs:
                self._inputs[delay] = calibration_inputs(self.pack, self.train, emd_s=delay)
            profile, result = calibrate_inputs(
                self.pack,
                self._inputs[delay],
                settings=self.settings,
                torque_basis=basis,
                force_scale=scale,
                start=self._plain.get(delay),
            )
            if plain:
                self._plain[delay] = result
            self._cache[key] = np.asarray(profile.f_max, dtype=float)
            self.reports[key] = profile.calibration
        return self._cache[key]

    def _force_scale(self, trial: TrialData, forces: dict[Effect, dict]) -> np.ndarray:
        """(T, G) the force factor of ``forces`` on every frame of ``trial`` (:func:`effects.force_factor`)."""
        mech, pack = trial.mechanics(self.pack), self.pack
        return force_factor(
            mech.lengths,
            mech.moment_arms,
            np.nan_to_num(trial.qd),
            *fibre_lengths(pack),
            forces,
        )

    def report(self, model: dict[Effect, dict]) -> dict | None:
        return self.reports.get(json.dumps(model, sort_keys=True))

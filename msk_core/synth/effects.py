"""Hidden effects: physiology present in the synthetic truth but absent from the default estimation model.

All are off by default. ``parse_effects("emd=0.06,fv,damping=0.8")`` switches some on; a bare name uses the default
parameter. Muscle curves follow Thelen (2003, J Biomech Eng 125:70) in simplified rigid-tendon form:
active force-length exp(−((l̃−1)/0.45)²), passive (exp(4(l̃−1)/0.6) − 1)/(exp(4) − 1) for l̃ > 1, force-velocity
Hill-type with v_max = 10 l_opt/s, curvature 0.25 when shortening and an eccentric plateau of 1.8.

Each effect has the name the estimator's model gives the same physics (:class:`msk_core.estimate.effects.Effect`,
which ``msk discrepancy`` names and profiles carry), except ``fatigue``, which changes the EMG spectrum and no torque.
This module does not import that one: the generator's truth stays independent of the model (see
:func:`muscle_factors`); ``tests/test_effects.py`` checks the names agree.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace

import numpy as np

from msk_core.errors import ConfigError

#: parameter used when an effect is named without a value
DEFAULTS = {
    "emd": 0.05,  # s, EMG leads force (electromechanical delay; 30-100 ms, Cavanagh & Komi 1979)
    "fl_active": 1.0,  # on/off
    "fl_passive": 1.0,
    "fv": 1.0,
    "damping": 0.5,  # N·m·s/rad at every coordinate
    # the trial files log reported = this x the true barbell mass (the estimator's load_misreport fits the inverse,
    # true_over_reported)
    "load_misreport": 1.1,
    "crosstalk": 0.15,  # fraction of each neighbour's source in an electrode's signal
    # per rep, the EMG spectrum compresses by this fraction: the median and mean frequency of rep k are
    # (1 - f (k - 1)) x rep 1's (slower fibre conduction as the muscle tires), a known shift for the fatigue index
    "fatigue": 0.015,
}


@dataclass(frozen=True)
class Effects:
    emd: float = 0.0
    fl_active: bool = False
    fl_passive: bool = False
    fv: bool = False
    damping: float = 0.0
    load_misreport: float = 1.0  # reported / true barbell mass (the trial files log the reported one)
    crosstalk: float = 0.0
    fatigue: float = 0.0  # spectral compression per rep (msk_core.synth.emg.spectral_scale)

    def active(self) -> dict[str, float | bool]:
        """Only the effects that are switched on (for the truth file and logs)."""
        off = Effects()
        return {k: v for k, v in asdict(self).items() if v != getattr(off, k)}

    def to_dict(self) -> dict:
        return asdict(self)

    @property
    def needs_muscle_state(self) -> bool:
        return self.fl_active or self.fl_passive or self.fv


def parse_effects(text: str | None) -> Effects:
    """``"emd=0.06,fl_active,damping=1.0"`` -> :class:`Effects`. Empty or ``"none"`` -> all off."""
    effects = Effects()
    if text is None or not text.strip() or text.strip().lower() == "none":
        return effects
    names = {f.name: f for f in fields(Effects)}
    for token in text.split(","):
        token = token.strip()
        if not token:
            continue
        name, _, value = token.partition("=")
        name = name.strip()
        if name not in names:
            raise ConfigError(f"unknown effect; known: {', '.join(names)}", field="effects", value=token)
        if names[name].type in ("bool", bool):
            if value and value.strip().lower() not in ("1", "true", "yes", "on"):
                raise ConfigError("boolean effect takes no value (or =on)", field="effects", value=token)
            effects = replace(effects, **{name: True})
            continue
        try:
            number = float(value) if value else DEFAULTS[name]
        except ValueError:
            raise ConfigError("effect value must be a number", field="effects", value=token) from None
        limits = {
            "emd": (0.0, 0.2),
            "damping": (0.0, 20.0),
            "load_misreport": (0.5, 2.0),
            "crosstalk": (0.0, 0.5),
            "fatigue": (0.0, 0.05),
        }
        lo, hi = limits[name]
        if not lo <= number <= hi:
            raise ConfigError(f"effect value must be in [{lo}, {hi}]", field="effects", value=token)
        # mypy checks a ** mapping's value type against every field, the booleans too; name is a float field here
        effects = replace(effects, **{name: number})  # type: ignore[arg-type]
    return effects


# The muscle curves of the truth. They are not msk_core.estimate.effects' curves on purpose: those are the estimator's
# model, with parameters msk discrepancy fits (width, strain, v_max, eccentric plateau) and a fibre-length clip of
# [0.3, 2.0] that is only a numerical guard; these are the simulated subject's, with Thelen's constants and its
# fibres held to [0.4, 1.8] l_opt. One shared definition would move the truth whenever the model changes, and the
# discrepancy tests would then test the model against itself. The two differ where it matters: on the demo deadlift
# (recordings/demo) 0.5-0.9 % of the (frame, group) fibre lengths lie outside [0.4, 1.8] (0.36-1.81 l_opt), which the
# truth holds at the edge and the model does not; the demo bench press stays inside both (0.49-1.45).


def active_force_length(l_norm: np.ndarray) -> np.ndarray:
    return np.exp(-(((l_norm - 1.0) / 0.45) ** 2))


def passive_force_length(l_norm: np.ndarray) -> np.ndarray:
    stretch = np.maximum(l_norm - 1.0, 0.0)
    return (np.exp(4.0 * stretch / 0.6) - 1.0) / (np.exp(4.0) - 1.0)


def force_velocity(v_norm: np.ndarray) -> np.ndarray:
    """v_norm = shortening velocity / v_max (positive = shortening)."""
    v = np.asarray(v_norm, dtype=float)
    shortening = np.maximum(1.0 - v, 0.0) / (1.0 + v / 0.25)
    u = np.maximum(-v, 0.0)
    lengthening = 1.0 + 0.8 * u / (u + 0.17)
    return np.where(v >= 0.0, shortening, lengthening)


def muscle_factors(
    effects: Effects,
    mtu_length: np.ndarray,
    mtu_velocity: np.ndarray,
    optimal_fiber_length: np.ndarray,
    tendon_slack_length: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(active multiplier fl·fv, passive fraction of F_max, normalised fibre length), rigid tendon, no pennation; the
    fibre length clipped to the subject's [0.4, 1.8] l_opt (independent of the estimator's model, see above)."""
    l_norm = np.clip((mtu_length - tendon_slack_length) / optimal_fiber_length, 0.4, 1.8)
    active = np.ones_like(l_norm)
    if effects.fl_active:
        active = active * active_force_length(l_norm)
    if effects.fv:
        v_norm = -mtu_velocity / (10.0 * optimal_fiber_length)  # lengthening MTU = negative shortening
        active = active * force_velocity(v_norm)
    passive = passive_force_length(l_norm) if effects.fl_passive else np.zeros_like(l_norm)
    return active, passive, l_norm

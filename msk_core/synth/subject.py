"""A synthetic subject: anthropometry, personal muscle strength, recruitment style and EMG electrode properties."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from msk_core.synth.rng import stream


@dataclass(frozen=True)
class Subject:
    """Everything person-specific the generator draws from the subject seed.

    ``f_max_factor`` multiplies the pack's reference F_max per group (the quantity calibration must recover);
    ``effort_weight`` and ``cocontraction`` make the true recruitment differ from min sum a² (static optimisation).
    EMG gains are the RMS amplitude of the raw signal at maximal activation (µV), as a per-electrode property.
    """

    seed: int
    mass_kg: float
    height_m: float
    groups: tuple[str, ...]
    f_max_factor: np.ndarray  # (n_groups,)
    effort_weight: np.ndarray  # (n_groups,) weights of a_g² in the recruitment objective
    cocontraction: np.ndarray  # (n_groups,) activation floor per unit effort
    emg_gain_uv: dict[str, float] = field(default_factory=dict)  # channel -> RMS µV at a = 1
    noise_floor_uv: float = 2.0  # RMS of the amplifier/skin noise (µV)

    def to_dict(self) -> dict:
        return {
            "seed": self.seed,
            "mass_kg": self.mass_kg,
            "height_m": self.height_m,
            "f_max_factor": dict(zip(self.groups, map(float, self.f_max_factor))),
            "effort_weight": dict(zip(self.groups, map(float, self.effort_weight))),
            "cocontraction": dict(zip(self.groups, map(float, self.cocontraction))),
            "emg_gain_uv": {k: float(v) for k, v in self.emg_gain_uv.items()},
            "noise_floor_uv": self.noise_floor_uv,
        }


def make_subject(
    seed: int,
    groups: list[str] | tuple[str, ...],
    channels: list[str] | tuple[str, ...] = (),
    *,
    f_max_range: tuple[float, float] = (0.8, 1.6),
) -> Subject:
    """Draw a subject. Groups get their strength factor from the group name's own stream, so the same seed gives the
    same factor for a group whichever pack (and group order) it appears in."""
    rng = stream(seed, "anthropometry")
    mass = float(np.clip(rng.normal(78.0, 9.0), 55.0, 110.0))
    height = float(np.clip(rng.normal(1.77, 0.07), 1.55, 2.0))
    lo, hi = f_max_range
    factors, weights, cc = [], [], []
    for g in groups:
        r = stream(seed, "group", g)
        # log-uniform so that 0.6x and 1.6x are equally "far" from 1
        factors.append(float(np.exp(r.uniform(np.log(lo), np.log(hi)))))
        weights.append(float(np.exp(r.normal(0.0, 0.4))))
        cc.append(float(r.uniform(0.02, 0.08)))
    gains = {c: float(stream(seed, "electrode", c).uniform(150.0, 600.0)) for c in channels}
    noise = float(stream(seed, "amplifier").uniform(1.0, 3.0))
    return Subject(
        seed=int(seed),
        mass_kg=round(mass, 2),
        height_m=round(height, 3),
        groups=tuple(groups),
        f_max_factor=np.asarray(factors),
        effort_weight=np.asarray(weights),
        cocontraction=np.asarray(cc),
        emg_gain_uv=gains,
        noise_floor_uv=noise,
    )

"""Subject profile: the calibrated, person-specific part of the model, saved as readable JSON.

Holds the pack it was calibrated for (name + version), per-group F_max (N) and scale factors against the pack's
reference, the phase prior N(mu, sigma^2), the EMG normalisation used, the calibration's convergence report and
provenance (trials, time, software), and the rep template on the phase coordinate (``phase_model``) from which the live
node tracks the phase when joint-angle messages carry none.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from msk_core.errors import EstimationError, FileFormatError, MskError
from msk_core.estimate.pack import PackLike
from msk_core.estimate.phase import PhaseModel
from msk_core.estimate.prior import PhasePrior
from msk_core.io.files import write_text_atomic

FORMAT = "msk-subject-profile"
FORMAT_VERSION = 1


@dataclass
class SubjectProfile:
    pack_name: str
    pack_version: str
    groups: list[str]
    f_max: np.ndarray
    f_max_ref: np.ndarray
    prior: PhasePrior | None = None
    emg_normalisation: dict[str, dict] = field(default_factory=dict)
    calibration: dict = field(default_factory=dict)
    provenance: dict = field(default_factory=dict)
    phase_model: PhaseModel | None = None  # rep template on the phase coordinate: the live node tracks the phase
    # model effects beyond F = F_max a found by `msk discrepancy` (msk_core.estimate.effects; versioned, with the
    # evidence); None: the plain model, and the JSON has no `effects` key (profiles without it behave as before)
    effects: dict | None = None
    source: Path | None = field(default=None, compare=False)  # the file it was loaded from, for messages

    @property
    def scale_factors(self) -> np.ndarray:
        return self.f_max / self.f_max_ref

    def check_pack(self, pack: PackLike) -> None:
        """The profile only makes sense with the pack it was calibrated on."""
        profile = "subject profile" if self.source is None else f"subject profile {self.source}"
        if pack.name != self.pack_name:
            raise EstimationError(
                f"{profile} was calibrated for pack {self.pack_name!r} ({len(self.groups)} groups), not for pack "
                f"{pack.name!r}: give a profile calibrated on {pack.name!r}, or --pack {self.pack_name}"
            )
        if list(pack.groups) != list(self.groups):
            missing = [g for g in pack.groups if g not in self.groups]
            extra = [g for g in self.groups if g not in pack.groups]
            differences = [f"the pack's {_few(missing)} are not in it"] if missing else []
            differences += [f"its {_few(extra)} are not in the pack"] if extra else []
            raise EstimationError(
                f"{profile} was calibrated on other groups of pack {pack.name!r}: "
                + "; ".join(differences or ["the same groups in another order"])
                + "; recalibrate"
            )
        if str(pack.version) != str(self.pack_version):
            raise EstimationError(
                f"{profile} was calibrated for pack {self.pack_name!r} version {self.pack_version!r}, "
                f"but the loaded pack is version {pack.version!r}; recalibrate"
            )

    def to_dict(self) -> dict:
        return {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "pack": {"name": self.pack_name, "version": str(self.pack_version)},
            "groups": {
                g: {"f_max_n": round(float(f), 3), "f_max_ref_n": round(float(r), 3), "scale": round(float(f / r), 5)}
                for g, f, r in zip(self.groups, self.f_max, self.f_max_ref)
            },
            "prior": self.prior.to_dict() if self.prior is not None else None,
            "emg_normalisation": self.emg_normalisation,
            "calibration": self.calibration,
            "provenance": self.provenance,
            "phase_model": None if self.phase_model is None else self.phase_model.to_dict(),
        } | ({} if self.effects is None else {"effects": self.effects})

    def save(self, path: str | Path) -> None:
        write_text_atomic(path, json.dumps(self.to_dict(), indent=2) + "\n")  # live sessions may be reading it

    @classmethod
    def load(cls, path: str | Path) -> SubjectProfile:
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except OSError as exc:
            raise FileFormatError(f"cannot read subject profile: {exc.strerror}", path=path) from None
        except json.JSONDecodeError as exc:
            raise FileFormatError(f"not valid JSON: {exc.msg}", path=path, line=exc.lineno) from None
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise FileFormatError("not a subject profile", path=path, field="format", value=data.get("format"))
        try:
            groups = list(data["groups"])
            f_max = np.array([data["groups"][g]["f_max_n"] for g in groups], dtype=float)
            f_ref = np.array([data["groups"][g]["f_max_ref_n"] for g in groups], dtype=float)
            prior = PhasePrior.from_dict(data["prior"]) if data.get("prior") else None
            phase_model = PhaseModel.from_dict(data["phase_model"]) if data.get("phase_model") else None
            return cls(
                pack_name=data["pack"]["name"],
                pack_version=str(data["pack"]["version"]),
                groups=groups,
                f_max=f_max,
                f_max_ref=f_ref,
                prior=prior,
                emg_normalisation=data.get("emg_normalisation", {}),
                calibration=data.get("calibration", {}),
                provenance=data.get("provenance", {}),
                phase_model=phase_model,
                effects=_checked_effects(data.get("effects"), groups, path),
                source=path,
            )
        except KeyError as exc:
            raise FileFormatError("missing field", path=path, field=str(exc.args[0])) from None
        except (TypeError, ValueError, MskError) as exc:
            raise FileFormatError(f"invalid value: {exc}", path=path) from None


def _few(names: list[str], shown: int = 5) -> str:
    """Group names for a message: the first ``shown`` and how many more."""
    more = len(names) - shown
    return ", ".join(names[:shown]) + (f" and {more} more" if more > 0 else "")


def _checked_effects(effects, groups: list[str], path: Path) -> dict | None:
    """The ``effects`` section as stored, after checking it parses (version, names, groups)."""
    if effects is None:
        return None
    from msk_core.estimate.effects import ModelEffects

    try:
        ModelEffects.from_dict(effects, groups, [])
    except EstimationError as exc:
        raise FileFormatError(str(exc), path=path, field="effects") from None
    return effects

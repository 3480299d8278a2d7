"""Phase-dependent activation prior N(mu(phase), sigma(phase)^2) per muscle group (the paper's EMG prior).

Stored as bin means/stds over the phase of a repetition, phase in [0, 1]; :meth:`PhasePrior.at` interpolates means
and precisions linearly between bin centres (clamped at the ends) so the prior is continuous in phase. Groups without
EMG carry a wide default prior (``NO_EMG_MEAN``, ``NO_EMG_STD``) which then acts as a weak min-activation regulariser,
and ``has_emg`` says so. :func:`msk_core.estimate.pipeline.build_prior` replaces that default by a derived prior
(minimal effort or a measured synergist, see ``sources``).

Between repetitions the subject rests, which no phase bin describes: the prior then has a ``rest`` state (mean/std of
the EMG outside the calibration reps), selected by ``REST_PHASE`` (msk_core.signal.reps: any negative phase).
``None``/NaN means the phase is unknown and selects the prior pooled over the rep phases.

A prior is learned at the load of its training trials. It may carry that load (``load_newton``) and the torques the
training reps needed per phase bin (``torque``, mean |tau| per coordinate): at another load the estimator then scales
the prior by the torque this lift needs against the training's at the same phase (:class:`LoadScale`; force is
F_max · a, so the activation a muscle needs grows with the torque it must make).

:func:`fit_phase_prior` fits it from reps (statistics across reps: each rep contributes one value per bin, so a slow rep
does not weigh more than a fast one, and sigma is the rep-to-rep variability).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from msk_core.errors import ConfigError, EstimationError
from msk_core.units import GRAVITY

# Groups without EMG: the prior must not pretend to know them. A zero mean with sigma 0.5 is a weak pull towards
# rest, weaker than any EMG-derived prior (typical sigma 0.02-0.2), so the torque term decides their activation.
NO_EMG_MEAN = 0.0
NO_EMG_STD = 0.5
# Floor on sigma: a phase bin in which every rep happened to give the same EMG must not become a hard constraint.
MIN_STD = 0.02
MIN_REST_SAMPLES = 5
#: Loads closer than this (N) to the prior's are the same load: its prior stands unscaled.
SAME_LOAD_N = 1.0
#: Repetitions over which the load scale averages this lift's torque against the training's (an exponential average
#: over rep frames whose length in frames comes from the phase's progress per frame: no clock, no frame rate).
LOAD_SCALE_REPS = 3.0
#: Bounds of the load scale: a prior is not stretched beyond what a few-fold load change could mean.
LOAD_SCALE_RANGE = (0.25, 4.0)


@dataclass(frozen=True)
class PhasePrior:
    """mean/std arrays of shape (n_bins, n_groups); ``has_emg`` (n_groups,) marks EMG-derived columns."""

    groups: tuple[str, ...]
    mean: np.ndarray
    std: np.ndarray
    has_emg: np.ndarray
    rest_mean: np.ndarray | None = None  # (n_groups,) prior between repetitions; None: use the pooled prior
    rest_std: np.ndarray | None = None
    # where each group's prior comes from: "emg", "min_effort", "synergist:<group>" or "default" (N(0, 0.5^2))
    sources: tuple[str, ...] | None = None
    # (n_bins, n_coordinates) mean |torque| of the training reps per phase bin, and their hand load (N): what the
    # load scale compares a lift at another load with; None: the prior is used as learned at every load
    torque: np.ndarray | None = None
    load_newton: float | None = None

    def __post_init__(self) -> None:
        if self.sources is not None and len(self.sources) != len(self.groups):
            raise EstimationError(f"prior sources must name {len(self.groups)} groups, got {len(self.sources)}")
        if self.mean.shape != self.std.shape or self.mean.ndim != 2 or self.mean.shape[1] != len(self.groups):
            raise EstimationError(
                f"prior arrays must be (n_bins, {len(self.groups)}); got mean {self.mean.shape}, std {self.std.shape}"
            )
        if not (np.all(np.isfinite(self.mean)) and np.all(self.std > 0)):
            raise EstimationError("prior means must be finite and standard deviations positive")
        if (self.rest_mean is None) != (self.rest_std is None):
            raise EstimationError("rest prior needs both mean and std")
        if (
            self.rest_mean is not None
            and self.rest_std is not None
            and (  # both or neither (checked above)
                self.rest_mean.shape != (len(self.groups),)
                or self.rest_std.shape != (len(self.groups),)
                or not np.all(self.rest_std > 0)
            )
        ):
            raise EstimationError(f"rest prior must be {len(self.groups)} means and positive stds")
        if (self.torque is None) != (self.load_newton is None):
            raise EstimationError("the prior's training torque and load go together: both or neither")
        if self.torque is not None and (
            self.torque.ndim != 2 or self.torque.shape[0] != self.n_bins or not np.all(np.isfinite(self.torque))
        ):
            raise EstimationError(
                f"prior torque must be finite, (n_bins={self.n_bins}, n_coordinates); got {self.torque.shape}"
            )
        if self.load_newton is not None and not (math.isfinite(self.load_newton) and self.load_newton >= 0.0):
            raise EstimationError(f"prior load_newton must be finite and >= 0, got {self.load_newton}")

    @property
    def n_bins(self) -> int:
        return self.mean.shape[0]

    def at(self, phase: float | None) -> tuple[np.ndarray, np.ndarray]:
        """(mu, sigma) at a phase in [0, 1]; ``REST_PHASE``: between reps (rest); ``None``/NaN: pooled over all phases.

        Means and precisions 1/sigma^2 are interpolated linearly between bin centres (clamped at the ends).
        """
        mu, prec = self.mean_precision(phase)
        return mu, 1.0 / np.sqrt(prec)

    def mean_precision(self, phase: float | None) -> tuple[np.ndarray, np.ndarray]:
        """(mu, 1/sigma^2) at a phase, from the cached :meth:`table` (the per-frame hot path)."""
        mean, prec, dmean, dprec = self._tables()
        i0, i1, frac = self.rows(phase)
        if i0 == i1:
            return mean[i0], prec[i0]
        return mean[i0] + frac * dmean[i0], prec[i0] + frac * dprec[i0]

    def table(self) -> tuple[np.ndarray, np.ndarray]:
        """(mean, precision) tables of shape (n_bins + 2, G): the phase bins, then the pooled prior (unknown phase),
        then the rest prior (between reps). :meth:`rows` says which rows a phase interpolates."""
        mean, prec, _, _ = self._tables()
        return mean, prec

    def rows(self, phase: float | None) -> tuple[int, int, float]:
        """(row0, row1, frac) of :meth:`table`: the prior at ``phase`` is row0 + frac * (row1 - row0), linear between
        bin centres and clamped at the ends; unknown phase (None/NaN) -> the pooled row, rest (negative) -> the rest
        row."""
        n = self.mean.shape[0]
        if phase is None or not math.isfinite(phase):
            return n, n, 0.0
        if phase < 0.0:
            return n + 1, n + 1, 0.0
        x = min(max(float(phase), 0.0), 1.0) * n - 0.5
        if x <= 0.0:
            return 0, 0, 0.0
        if x >= n - 1:
            return n - 1, n - 1, 0.0
        i = int(x)
        return i, i + 1, x - i

    def _tables(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        cache = self.__dict__.get("_cache")
        if cache is None:
            mu_p, sd_p = self.pooled()
            rest_mu, rest_sd = (
                (mu_p, sd_p) if self.rest_mean is None or self.rest_std is None else (self.rest_mean, self.rest_std)
            )
            mean = np.vstack([self.mean, mu_p, rest_mu])
            prec = np.vstack([1.0 / self.std**2, 1.0 / sd_p**2, 1.0 / rest_sd**2])
            cache = (mean, prec, np.diff(mean, axis=0), np.diff(prec, axis=0))
            object.__setattr__(self, "_cache", cache)
        return cache

    def pooled(self) -> tuple[np.ndarray, np.ndarray]:
        """Mixture of all bins: mean of means, std from the law of total variance."""
        mu = self.mean.mean(axis=0)
        var = (self.std**2).mean(axis=0) + self.mean.var(axis=0)
        return mu, np.sqrt(var)

    def to_dict(self) -> dict:
        return {
            "n_bins": self.n_bins,
            "groups": list(self.groups),
            "has_emg": [bool(x) for x in self.has_emg],
            "mean": self.mean.round(6).tolist(),
            "std": self.std.round(6).tolist(),
            "rest_mean": None if self.rest_mean is None else self.rest_mean.round(6).tolist(),
            "rest_std": None if self.rest_std is None else self.rest_std.round(6).tolist(),
            "sources": None if self.sources is None else list(self.sources),
            "torque": None if self.torque is None else self.torque.round(4).tolist(),
            "load_newton": self.load_newton,
        }

    @classmethod
    def from_dict(cls, data: dict) -> PhasePrior:
        return cls(
            groups=tuple(data["groups"]),
            mean=np.asarray(data["mean"], dtype=float),
            std=np.asarray(data["std"], dtype=float),
            has_emg=np.asarray(data["has_emg"], dtype=bool),
            rest_mean=None if data.get("rest_mean") is None else np.asarray(data["rest_mean"], dtype=float),
            rest_std=None if data.get("rest_std") is None else np.asarray(data["rest_std"], dtype=float),
            sources=None if data.get("sources") is None else tuple(data["sources"]),
            torque=None if data.get("torque") is None else np.asarray(data["torque"], dtype=float),
            load_newton=None if data.get("load_newton") is None else float(data["load_newton"]),
        )

    def torque_at(self, phase: float) -> np.ndarray | None:
        """The training reps' mean |torque| per coordinate at a rep phase in [0, 1] (interpolated as the prior);
        None without a training torque."""
        if self.torque is None:
            return None
        i0, i1, frac = self.rows(phase)
        return self.torque[i0] if i0 == i1 else self.torque[i0] + frac * (self.torque[i1] - self.torque[i0])


@dataclass
class LoadScale:
    """Explicit state of the load-scaled prior: per group, how much more (or less) torque this lift needs than the
    training reps needed at the same phases, over the last ``LOAD_SCALE_REPS`` repetitions.

    s_g = sum_t sum_n |R_ng| |tau_n(t)| / sum_t sum_n |R_ng| |tau_train,n(phase(t))| over the rep frames t (its
    coordinates weighted by the group's moment arms; each frame weighs the same, older frames forgotten
    exponentially over ``LOAD_SCALE_REPS`` reps, counted in frames from the phase's mean progress per frame). The
    prior of group g is then N(b_g + s_g (mu_g - b_g), (s_g sigma_g)^2), b_g = min(mu_g, its rest mean): what the
    muscle does above its tone at rest grows with the load, the tone does not.
    Only at a load other than the prior's (a different load is what the torques then differ by; at the same load they
    differ by technique, which the prior learned as it is) and only inside reps (the rest prior stands). The sums
    start at zero, so the first frames weigh no more than later ones; until the phase has moved, the prior stands."""

    prior: PhasePrior
    load_newton: float | None = None  # the load of the frames (N); None: not known, no scaling
    _num: np.ndarray | None = None  # forgetting sums of this lift's and the training's torque demand per group
    _den: np.ndarray | None = None
    _last_phase: float | None = None
    _step: float | None = None  # mean phase progress per rep frame (1 / frames per rep)
    frames: int = 0  # frames whose prior was scaled, since the estimator began
    scale_sum: np.ndarray | None = None  # their scales summed per group (for the mean a report shows)

    @property
    def active(self) -> bool:
        """Whether the load differs from the prior's (and the prior knows its training torque)."""
        return (
            self.prior.load_newton is not None
            and self.load_newton is not None
            and abs(self.load_newton - self.prior.load_newton) > SAME_LOAD_N
        )

    def set_load(self, load_newton: float | None) -> None:
        """The frames' load; a change restarts the average (the torque ratio of the old load says nothing now)."""
        if load_newton != self.load_newton:
            self.load_newton = load_newton
            self.reset()

    def reset(self) -> None:
        self._num = self._den = self._last_phase = self._step = None

    def update(self, arms: np.ndarray, tau: np.ndarray, phase: float | None) -> np.ndarray | None:
        """The scale per group for this frame (moment arms (n, G), torques (n,)); None where the prior stands as
        learned (same or unknown load, no training torque, outside reps, no progress yet)."""
        if not self.active or phase is None or not (0.0 <= phase <= 1.0):
            return None
        train = self.prior.torque_at(phase)
        if train is None or train.shape != tau.shape:
            return None
        if self._last_phase is not None:
            step = phase - self._last_phase
            step = step + 1.0 if step < -0.5 else step  # the next rep began
            if step > 0.0:
                self._step = step if self._step is None else 0.9 * self._step + 0.1 * step
        self._last_phase = phase
        weights = np.abs(arms).T
        num, den = weights @ np.abs(tau), weights @ train
        if self._num is None or self._den is None:
            self._num, self._den = np.zeros_like(num), np.zeros_like(den)
        k = 0.0 if self._step is None else min(1.0, self._step / LOAD_SCALE_REPS)
        self._num = (1.0 - k) * self._num + k * num
        self._den = (1.0 - k) * self._den + k * den
        if not np.any(self._den > 0.0):
            return None
        lo, hi = LOAD_SCALE_RANGE
        ratio = np.clip(np.divide(self._num, self._den, out=np.ones_like(self._num), where=self._den > 0.0), lo, hi)
        self.frames += 1
        self.scale_sum = ratio.copy() if self.scale_sum is None else self.scale_sum + ratio
        return ratio

    def summary(self) -> dict | None:
        """What the scale did, for reports: the prior's load and the last frames' (kg), the frames scaled and the
        mean scale per group; None when no frame was scaled."""
        if not self.frames or self.scale_sum is None or self.prior.load_newton is None:
            return None
        return {
            "prior_load_kg": self.prior.load_newton / GRAVITY,
            "load_kg": None if self.load_newton is None else self.load_newton / GRAVITY,
            "frames": self.frames,
            "mean_scale": dict(zip(self.prior.groups, (self.scale_sum / self.frames).round(3).tolist())),
        }


def load_scale_line(trial: str, summary: dict) -> str:
    """One line for a person: how the prior was scaled to ``trial``'s load (:meth:`LoadScale.summary`), as
    ``msk estimate`` prints it and ``msk evaluate``'s report writes it."""
    values = summary["mean_scale"].values()
    return (
        f"{trial}: the prior, learned at {summary['prior_load_kg']:g} kg, was scaled to the trial's "
        f"{summary['load_kg']:g} kg on {summary['frames']} rep frames (mean scale per group "
        f'{min(values):.2f}-{max(values):.2f}; docs/estimation.md, "The prior at another load").'
    )


def phase_bins(phases: np.ndarray, n_bins: int) -> np.ndarray:
    """The prior's bin of each phase in [0, 1] (unknown phases in the first; what the prior and its training torque
    are binned by)."""
    return np.minimum((np.clip(np.nan_to_num(phases, nan=0.0), 0.0, 1.0) * n_bins).astype(int), n_bins - 1)


def fit_phase_prior(
    groups: Sequence[str],
    emg: dict[str, np.ndarray],
    phases: np.ndarray,
    rep_index: np.ndarray,
    *,
    n_bins: int = 20,
) -> PhasePrior:
    """Per group and phase bin, mean and std across repetitions of each rep's bin-mean normalised EMG.

    ``emg`` maps group -> envelope samples aligned with ``phases``/``rep_index`` (rep_index < 0 = outside any rep, where
    the phase is ``REST_PHASE``).
    With a single repetition the std is the within-bin std (there is no across-rep spread to measure). Samples outside
    any rep (at least ``MIN_REST_SAMPLES``) give the rest prior: their mean and std per group.
    """
    n_groups = len(groups)
    mean = np.full((n_bins, n_groups), NO_EMG_MEAN)
    std = np.full((n_bins, n_groups), NO_EMG_STD)
    has_emg = np.zeros(n_groups, dtype=bool)
    in_rep = rep_index >= 0
    have_rest = int((~in_rep).sum()) >= MIN_REST_SAMPLES
    rest_mean = np.full(n_groups, NO_EMG_MEAN)
    rest_std = np.full(n_groups, NO_EMG_STD)
    if not np.any(in_rep):
        raise EstimationError("no repetition found: cannot build a phase prior")
    reps, rep_frames = np.unique(rep_index[in_rep], return_counts=True)
    if n_bins > rep_frames.max():  # every rep would leave bins empty: a prior made of its neighbours' fill
        raise ConfigError(
            f"{n_bins} phase bins, but the longest of the {len(reps)} repetitions has {int(rep_frames.max())} frames: "
            f"choose at most {int(rep_frames.min())} bins (each rep then has a frame in every bin; default 20)",
            field="bins",
            value=n_bins,
        )
    bins = phase_bins(phases, n_bins)
    for g, name in enumerate(groups):
        if name not in emg:
            continue
        has_emg[g] = True
        x = np.asarray(emg[name], dtype=float)
        per_rep = np.full((len(reps), n_bins), np.nan)
        within = np.full((len(reps), n_bins), np.nan)
        for k, r in enumerate(reps):
            for b in range(n_bins):
                sel = (rep_index == r) & (bins == b) & np.isfinite(x)
                if np.any(sel):
                    per_rep[k, b] = x[sel].mean()
                    within[k, b] = x[sel].std()
        with warnings.catch_warnings():  # a bin no rep reached (short reps) is NaN here and filled from its neighbours
            warnings.simplefilter("ignore", RuntimeWarning)
            mean[:, g] = fill_empty_bins(np.nanmean(per_rep, axis=0))
            spread = np.nanstd(per_rep, axis=0, ddof=1) if len(reps) > 1 else within[0]
        std[:, g] = np.maximum(fill_empty_bins(spread), MIN_STD)
        rest = x[~in_rep & np.isfinite(x)]
        if rest.size >= MIN_REST_SAMPLES:
            rest_mean[g], rest_std[g] = rest.mean(), max(rest.std(), MIN_STD)
    return PhasePrior(
        groups=tuple(groups),
        mean=mean,
        std=std,
        has_emg=has_emg,
        rest_mean=rest_mean if have_rest else None,
        rest_std=rest_std if have_rest else None,
    )


def fill_empty_bins(x: np.ndarray) -> np.ndarray:
    """Empty bins take the value of the nearest filled bin (interpolated)."""
    ok = np.isfinite(x)
    if not np.any(ok):
        return np.zeros_like(x)
    idx = np.arange(len(x))
    return np.interp(idx, idx[ok], x[ok])

"""Per muscle group and phase bin: mean and standard deviation of normalised EMG across reps — the N(mu, sigma^2)
prior on activation. Stored with the subject profile as a plain dict (JSON-ready).

Statistics are across reps: each rep contributes one value per bin (its mean over the samples in that bin), so a
slow rep does not weigh more than a fast one, and sigma is the rep-to-rep variability.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from msk_core.errors import ConfigError, InputError


@dataclass(frozen=True)
class PhasePriors:
    """``mean[b, g]``, ``std[b, g]`` of group ``groups[g]`` in phase bin ``b`` (bins of width ``1 / n_bins``)."""

    groups: tuple[str, ...]
    mean: np.ndarray
    std: np.ndarray
    n_reps: np.ndarray  # reps that contributed to each (bin, group)

    @property
    def n_bins(self) -> int:
        return int(self.mean.shape[0])

    def bin_of(self, phase: np.ndarray | float) -> np.ndarray:
        """Bin index of each phase in [0, 1); -1 for ``nan`` (no rep under way)."""
        ph = np.asarray(phase, dtype=float)
        out = np.full(ph.shape, -1, dtype=int)
        ok = np.isfinite(ph)
        out[ok] = np.clip((ph[ok] * self.n_bins).astype(int), 0, self.n_bins - 1)
        return out

    def at(self, phase: float) -> tuple[np.ndarray, np.ndarray]:
        """``(mu, sigma)`` per group at ``phase``. Outside a rep (``nan``) the prior is the pooled one: the mean over
        bins, with sigma widened to cover the spread of the bin means (an honest "don't know the phase")."""
        b = int(self.bin_of(phase))
        if b >= 0:
            return self.mean[b].copy(), self.std[b].copy()
        mu = self.mean.mean(axis=0)
        sigma = np.sqrt((self.std**2).mean(axis=0) + self.mean.var(axis=0))
        return mu, sigma

    def to_dict(self) -> dict[str, object]:
        return {
            "groups": list(self.groups),
            "n_bins": self.n_bins,
            "mean": self.mean.tolist(),
            "std": self.std.tolist(),
            "n_reps": self.n_reps.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict[str, object]) -> PhasePriors:
        try:
            groups = tuple(str(g) for g in d["groups"])  # type: ignore[attr-defined]
            mean = np.asarray(d["mean"], dtype=float)
            std = np.asarray(d["std"], dtype=float)
            n_reps = np.asarray(d["n_reps"], dtype=int)
        except KeyError as exc:
            raise ConfigError("phase priors miss a field", field=str(exc.args[0])) from None
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"invalid phase priors: {exc}", field="priors") from exc
        shape = (int(d.get("n_bins", mean.shape[0])), len(groups))  # type: ignore[call-overload]
        for name, arr in (("mean", mean), ("std", std), ("n_reps", n_reps)):
            if arr.shape != shape:
                raise ConfigError(f"expected shape {shape}", field=name, value=arr.shape)
        if np.any(~np.isfinite(std)) or np.any(std <= 0):
            raise ConfigError("std must be finite and > 0", field="std")
        return cls(groups=groups, mean=mean, std=std, n_reps=n_reps)


def average_groups(emg: np.ndarray, labels: list[str], groups: dict[str, list[str]]) -> tuple[np.ndarray, list[str]]:
    """Columns of ``emg`` ``(n, len(labels))`` averaged per muscle group (e.g. left and right erector spinae
    channels into one group). Returns ``(n, len(groups))`` and the group names in ``groups`` order."""
    x = np.asarray(emg, dtype=float)
    if x.ndim != 2 or x.shape[1] != len(labels):
        raise InputError(f"expected {len(labels)} EMG columns", field="emg", value=x.shape)
    cols = []
    for name, members in groups.items():
        missing = [m for m in members if m not in labels]
        if not members or missing:
            raise InputError(f"group {name!r} names unknown channels {missing}; channels: {', '.join(labels)}",
                             field=name, value=members)
        cols.append(x[:, [labels.index(m) for m in members]].mean(axis=1))
    return np.column_stack(cols), list(groups)


def fit_priors(
    phase: np.ndarray,
    rep_index: np.ndarray,
    emg: np.ndarray,
    groups: list[str] | tuple[str, ...],
    *,
    n_bins: int = 20,
    min_std: float = 0.01,
) -> PhasePriors:
    """Fit priors from samples with ``phase`` in [0, 1) (``nan`` outside reps), their rep index (-1 outside) and
    normalised EMG ``(n_samples, n_groups)``. ``min_std`` floors sigma (one rep, or identical reps, would otherwise
    give a zero-width prior). Bins no rep visited take the mean/std of all in-rep samples of that group."""
    ph = np.asarray(phase, dtype=float).reshape(-1)
    idx = np.asarray(rep_index).reshape(-1)
    x = np.asarray(emg, dtype=float)
    if x.ndim == 1:
        x = x[:, None]
    if not (ph.shape[0] == idx.shape[0] == x.shape[0]):
        raise InputError("phase, rep_index and emg lengths differ", field="emg",
                         value=(ph.shape[0], idx.shape[0], x.shape[0]))
    if x.shape[1] != len(groups):
        raise InputError(f"{len(groups)} group names for {x.shape[1]} EMG columns", field="groups")
    if n_bins < 1:
        raise ConfigError("n_bins must be >= 1", field="n_bins", value=n_bins)
    inside = np.isfinite(ph) & (idx >= 0) & np.all(np.isfinite(x), axis=1)
    if not inside.any():
        raise InputError("no sample lies inside a repetition", field="phase")
    if np.any((ph[inside] < 0) | (ph[inside] >= 1)):
        raise InputError("phase must be in [0, 1)", field="phase")
    bins = np.zeros(ph.shape[0], dtype=int)
    bins[inside] = np.clip((ph[inside] * n_bins).astype(int), 0, n_bins - 1)
    reps = np.unique(idx[inside])
    # per (rep, bin): mean over that rep's samples in the bin
    per = np.full((reps.shape[0], n_bins, x.shape[1]), np.nan)
    for r_i, r in enumerate(reps):
        m = inside & (idx == r)
        sums = np.zeros((n_bins, x.shape[1]))
        np.add.at(sums, bins[m], x[m])
        counts = np.bincount(bins[m], minlength=n_bins)
        seen = counts > 0
        per[r_i, seen] = sums[seen] / counts[seen, None]
    seen_any = np.isfinite(per)
    n_reps = seen_any.sum(axis=0)
    filled = np.where(seen_any, per, 0.0)
    mean = filled.sum(axis=0) / np.maximum(n_reps, 1)
    dev2 = np.where(seen_any, (per - mean) ** 2, 0.0).sum(axis=0)
    std = np.sqrt(dev2 / np.maximum(n_reps - 1, 1))  # across reps, ddof=1; 0 for a single rep (floored below)
    empty = n_reps[:, 0] == 0
    if empty.any():
        mean[empty] = x[inside].mean(axis=0)
        std[empty] = x[inside].std(axis=0)
    std = np.maximum(std, min_std)
    return PhasePriors(groups=tuple(groups), mean=mean, std=std, n_reps=n_reps)

"""Evaluation metrics: activation RMSE against measured (normalised EMG) activation, torque tracking R and RMSE."""

from __future__ import annotations

import numpy as np


def rmse(a: np.ndarray, b: np.ndarray) -> float:
    """Root mean square of a - b over the samples where both are finite (NaN when none)."""
    ok = np.isfinite(a) & np.isfinite(b)
    return float(np.sqrt(np.mean((a[ok] - b[ok]) ** 2))) if np.any(ok) else float("nan")


CONSTANT_RELATIVE_STD = 1e-9  # a series varying less than this, relative to its size, is constant: no r, no lag


def pearson_r(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson r over the frames where both are finite; NaN with fewer than 3, or when either is constant (to
    rounding: a constant estimate's last-digit noise would otherwise correlate with anything, at any lag)."""
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 3 or _constant(a[ok]) or _constant(b[ok]):
        return float("nan")
    return float(np.corrcoef(a[ok], b[ok])[0, 1])


def _constant(x: np.ndarray) -> bool:
    return bool(np.std(x) <= CONSTANT_RELATIVE_STD * max(float(np.max(np.abs(x))), 1e-300))


def activation_rmse(estimated: np.ndarray, groups: list[str], measured: dict[str, np.ndarray]) -> dict[str, float]:
    """RMSE per group that has a measurement, plus ``mean`` over those groups."""
    out = {g: rmse(estimated[:, groups.index(g)], np.asarray(x, dtype=float)) for g, x in measured.items()}
    values = [v for v in out.values() if np.isfinite(v)]
    out["mean"] = float(np.mean(values)) if values else float("nan")
    return out


def torque_tracking(
    model: np.ndarray, reference: np.ndarray, coordinates: list[str], body_mass_kg: float | None
) -> dict[str, dict[str, float]]:
    """Per coordinate: Pearson R, RMSE in N·m and (with a body mass) N·m/kg, of model vs inverse-dynamics torque,
    and the gain: the least-squares factor from the inverse-dynamics torque to the model's (1: all of it; R alone is
    blind to scale, so a model that gives half the torque at every instant has R 1)."""
    out = {}
    for j, c in enumerate(coordinates):
        e = rmse(model[:, j], reference[:, j])
        out[c] = {
            "r": pearson_r(model[:, j], reference[:, j]),
            "gain": torque_gain(model[:, j], reference[:, j]),
            "rmse_nm": e,
            "rmse_nm_per_kg": e / body_mass_kg if body_mass_kg else float("nan"),
        }
    return out


def torque_gain(model: np.ndarray, reference: np.ndarray) -> float:
    """The factor k minimising |model - k reference| over the finite samples (NaN without a reference torque)."""
    ok = np.isfinite(model) & np.isfinite(reference)
    denominator = float(np.sum(reference[ok] ** 2))
    return float(np.sum(model[ok] * reference[ok]) / denominator) if denominator > 0 else float("nan")


def cross_correlation_lag(
    estimated: list[np.ndarray], measured: list[np.ndarray], dt: float, max_lag_s: float
) -> float:
    """Lag (s) at which the Pearson correlation of the estimate, shifted back by the lag, with the measurement peaks,
    over lags within ``max_lag_s``; positive: the estimate comes later than the measurement. Each pair of arrays is
    one trial (pairs are formed within a trial only and pooled across trials); parabolic refinement around the best
    lag. NaN when no lag has three finite pairs with spread in both."""
    n_lag = max(int(round(max_lag_s / dt)), 0)
    lags = np.arange(-n_lag, n_lag + 1)
    corr = np.full(lags.size, np.nan)
    for k, lag in enumerate(lags):
        est, ref = [], []
        for e, m in zip(estimated, measured):
            n = min(e.size, m.size)
            if abs(lag) >= n:
                continue
            if lag >= 0:  # estimate at t + lag against measurement at t
                est.append(e[lag:n])
                ref.append(m[: n - lag])
            else:
                est.append(e[: n + lag])
                ref.append(m[-lag:n])
        if est:
            corr[k] = pearson_r(np.concatenate(est), np.concatenate(ref))
    if not np.any(np.isfinite(corr)):
        return float("nan")
    best = int(np.nanargmax(corr))
    shift = 0.0
    if 0 < best < lags.size - 1 and np.all(np.isfinite(corr[best - 1 : best + 2])):
        y0, y1, y2 = corr[best - 1 : best + 2]
        curvature = y0 - 2.0 * y1 + y2
        if curvature < 0:
            shift = float(0.5 * (y0 - y2) / curvature)
    return float((lags[best] + shift) * dt)


def on_off_agreement(estimated: np.ndarray, measured: np.ndarray, threshold: float) -> float:
    """Share of the frames (both finite) on which estimate and measurement agree about the muscle being on (above
    ``threshold``) or off (NaN when none)."""
    ok = np.isfinite(estimated) & np.isfinite(measured)
    if not np.any(ok):
        return float("nan")
    return float(np.mean((estimated[ok] > threshold) == (measured[ok] > threshold)))

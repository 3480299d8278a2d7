"""Evaluation metrics: activation RMSE against measured (normalised EMG) activation, torque tracking R and RMSE."""

from __future__ import annotations

import numpy as np


def rmse(a: np.ndarray, b: np.ndarray) -> float:
    """Root mean square of a - b over the samples where both are finite (NaN when none)."""
    ok = np.isfinite(a) & np.isfinite(b)
    return float(np.sqrt(np.mean((a[ok] - b[ok]) ** 2))) if np.any(ok) else float("nan")


def pearson_r(a: np.ndarray, b: np.ndarray) -> float:
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 3 or np.std(a[ok]) == 0 or np.std(b[ok]) == 0:
        return float("nan")
    return float(np.corrcoef(a[ok], b[ok])[0, 1])


def activation_rmse(estimated: np.ndarray, groups: list[str], measured: dict[str, np.ndarray]) -> dict[str, float]:
    """RMSE per group that has a measurement, plus ``mean`` over those groups."""
    out = {g: rmse(estimated[:, groups.index(g)], np.asarray(x, dtype=float)) for g, x in measured.items()}
    values = [v for v in out.values() if np.isfinite(v)]
    out["mean"] = float(np.mean(values)) if values else float("nan")
    return out


def torque_tracking(
    model: np.ndarray, reference: np.ndarray, coordinates: list[str], body_mass_kg: float | None
) -> dict[str, dict[str, float]]:
    """Per coordinate: Pearson R, RMSE in N·m and (with a body mass) N·m/kg, of model vs inverse-dynamics torque."""
    out = {}
    for j, c in enumerate(coordinates):
        e = rmse(model[:, j], reference[:, j])
        out[c] = {
            "r": pearson_r(model[:, j], reference[:, j]),
            "rmse_nm": e,
            "rmse_nm_per_kg": e / body_mass_kg if body_mass_kg else float("nan"),
        }
    return out

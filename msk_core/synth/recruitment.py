"""True recruitment: a per-subject weighted effort criterion with co-contraction floors and slow variability.

Per frame: minimise Σ_g w_g(t) a_g² subject to Σ_g r_ng F_g (m_g a_g + p_g) = τ_n (every coordinate) and
floor_g(t) ≤ a_g ≤ 1, where w_g(t) = subject weight × slowly varying log-normal noise, floor_g(t) = tone + c_g × effort(t)
(antagonists co-contract in proportion to the effort), m_g the active force-length-velocity multiplier and p_g the
passive force fraction. This is deliberately *not* min Σ a² (static optimisation), so estimators are tested against
something they do not assume. Frames whose torque the muscles cannot produce fall back to the least-squares compromise
and are reported through the residual.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import piqp
from scipy import signal

from msk_core.synth.rng import stream

TONE = 0.01  # resting activation


@dataclass(frozen=True)
class Recruitment:
    activation: np.ndarray  # (n_frames, n_groups)
    muscle_torque: np.ndarray  # (n_frames, n_coordinates) produced by the activations
    residual: np.ndarray  # muscle torque − required torque
    fallback_frames: int


def smooth_noise(n: int, n_channels: int, rate_hz: float, cutoff_hz: float, rng: np.random.Generator) -> np.ndarray:
    """Unit-variance Gaussian noise low-passed at ``cutoff_hz`` (zero-phase), shape (n, n_channels)."""
    pad = int(3 * rate_hz / cutoff_hz)
    white = rng.normal(size=(n + 2 * pad, n_channels))
    sos = signal.butter(2, cutoff_hz, fs=rate_hz, output="sos")
    x = signal.sosfiltfilt(sos, white, axis=0)[pad : pad + n]
    return x / max(float(x.std()), 1e-12)


def _solver(eps: float = 1e-10) -> piqp.DenseSolver:
    solver = piqp.DenseSolver()
    solver.settings.eps_abs = eps
    solver.settings.eps_rel = eps
    solver.settings.max_iter = 200
    solver.settings.verbose = False
    return solver


def recruit(
    moment_arms: np.ndarray,
    torque: np.ndarray,
    f_max: np.ndarray,
    effort_weight: np.ndarray,
    cocontraction: np.ndarray,
    *,
    rate_hz: float,
    seed: int,
    key: tuple,
    active_factor: np.ndarray | None = None,
    passive_factor: np.ndarray | None = None,
    variability: float = 0.15,
) -> Recruitment:
    """Solve the true recruitment for every frame.

    moment_arms (n_frames, n_coordinates, n_groups) m; torque (n_frames, n_coordinates) N·m the muscles must produce;
    f_max (n_groups,) the subject's N; optional active/passive factors (n_frames, n_groups) from the effects.
    """
    n_frames, n_coord, n_groups = moment_arms.shape
    active_factor = np.ones((n_frames, n_groups)) if active_factor is None else active_factor
    passive_factor = np.zeros((n_frames, n_groups)) if passive_factor is None else passive_factor
    rng = stream(seed, "recruitment", *key)
    weights = effort_weight[None, :] * np.exp(variability * smooth_noise(n_frames, n_groups, rate_hz, 0.5, rng))
    capacity = np.abs(moment_arms) @ f_max  # (n_frames, n_coord) N·m if every muscle pulled fully
    effort = np.max(np.abs(torque) / np.maximum(capacity, 1e-9) * 4.0, axis=1).clip(0.0, 1.0)
    floors = np.minimum(TONE + cocontraction[None, :] * effort[:, None], 0.3)
    scale = np.maximum(np.abs(torque).max(axis=0), 1.0)  # per-coordinate torque scale for the soft fallback
    activation = np.empty((n_frames, n_groups))
    muscle = np.empty((n_frames, n_coord))
    fallbacks = 0
    ub = np.ones(n_groups)
    for k in range(n_frames):
        a_mat = moment_arms[k] * (f_max * active_factor[k])[None, :]
        b = torque[k] - moment_arms[k] @ (f_max * passive_factor[k])
        p = np.asfortranarray(np.diag(2.0 * weights[k]))
        c = np.zeros(n_groups)
        lb = floors[k]
        solver = _solver()
        solver.setup(p, c, A=np.asfortranarray(a_mat), b=b, x_l=lb, x_u=ub)
        status = solver.solve()
        if status != piqp.PIQP_SOLVED:
            # beyond capacity: least-squares torque match (dominant) plus the effort term
            fallbacks += 1
            at = a_mat / scale[:, None]
            bt = b / scale
            p = np.asfortranarray(2.0 * (1e4 * at.T @ at + np.diag(weights[k])))
            solver = _solver(1e-9)
            solver.setup(p, -2.0 * 1e4 * at.T @ bt, x_l=np.zeros(n_groups), x_u=ub)
            solver.solve()
        a = np.clip(solver.result.x, 0.0, 1.0)
        activation[k] = a
        muscle[k] = a_mat @ a + moment_arms[k] @ (f_max * passive_factor[k])
    return Recruitment(activation, muscle, muscle - torque, fallbacks)

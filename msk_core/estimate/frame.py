"""Per-frame activation estimation with a warm PIQP solver (the paper's second optimisation and its baselines).

Model: group force F_g = F_max,g * a_g (no force-length-velocity scaling), model torque tau_m = R(q) F, with R the
pack's moment arms (n_coordinates x n_groups). Torque residuals are scaled per coordinate by that coordinate's muscle
torque capacity at the current pose, c_n = sum_g |R_ng| F_max,g (floored at ``MIN_TORQUE_SCALE`` N·m), so that a
residual is a fraction of what the muscles can produce and no joint dominates by its units.

Methods (a within [a_min, a_max] per group, default [0, 1] - OpenSim bounds by each muscle's min_control;
A = R diag(F_max), A~ = diag(1/c) A, tau~ = tau / c):

- ``so``:       min sum a^2  s.t.  A~ a = tau~. When the torque is beyond the muscles' capacity (the equality problem
  is infeasible) the frame falls back to  min sum a^2 + RESERVE_WEIGHT * |A~ a - tau~|^2  and is flagged
  ``reserve`` (the residual is what a reserve actuator would have to add).
- ``hybrid``:   min |A~ a - tau~|^2 + hybrid_weight * sum a^2  (hybrid_weight 0.1 by default).
- ``proposed``: min 1/2 |A~ a - tau~|^2 / eps^2 + 1/2 sum ((a - mu(phase)) / sigma(phase))^2, i.e. the MAP estimate
  with torque noise eps * c_n (``torque_tolerance`` eps, default 0.01 = 1 % of capacity) and the subject's
  N(mu, sigma^2) prior at the current phase of the repetition (the rest prior between repetitions, phase < 0;
  pooled over phases when the phase is unknown, None/NaN).
- ``prior``:    a = mu(phase) clipped to [0, 1], no torque term (the prior-alone baseline).

One PIQP solver per estimator (dense, or sparse from 40 groups up: :mod:`msk_core.estimate.qp`) is set up on the
first frame and then only ``update()``-d with the new matrices, so its workspace and preconditioner
(``preconditioner_reuse_on_update``) are reused frame after frame.
(PIQP is an interior-point method: it takes no primal starting point, so "warm" means the reused workspace and
scaling. A KKT-verified re-solve on last frame's active set was tried and measured no faster in numpy.)
``step()`` never raises on bad data: NaN
input, infeasible torques or solver failures come back as a flagged :class:`FrameResult` and are counted in
:attr:`FrameEstimator.flag_counts` (a warning is logged on the first occurrence of each flag). Poses up to
``CLAMP_TOLERANCE`` (5 deg) outside the pack's fitted ranges are clamped into them (``clamped``, counted as
``out_of_range_clamped``); further out the frame is ``invalid_input`` rather than an extrapolated number.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from enum import Enum
from typing import TYPE_CHECKING

import numpy as np
import piqp

from msk_core.errors import EstimationError
from msk_core.estimate.laplace import laplace_std
from msk_core.estimate.pack import PackLike, resolve_pack
from msk_core.estimate.prior import PhasePrior
from msk_core.estimate.qp import Backend, EqualityQP, LeastSquaresQP, resolve_backend

if TYPE_CHECKING:
    from msk_core.estimate.profile import SubjectProfile

log = logging.getLogger(__name__)

MIN_TORQUE_SCALE = 1.0  # N·m; floor of the per-coordinate residual scale (coordinates almost no muscle crosses)
RESERVE_WEIGHT = 1.0e4  # weight of the scaled residual in the `so` reserve fallback
BOUND_TOL = 1.0e-6  # an activation this close to 0 or 1 counts as at its bound (Laplace free set)
CLAMP_TOLERANCE = np.deg2rad(5.0)  # poses this far outside a pack's fitted range are clamped (and counted)


class Method(str, Enum):
    PROPOSED = "proposed"
    SO = "so"
    HYBRID = "hybrid"
    PRIOR = "prior"


class FrameStatus(str, Enum):
    SOLVED = "solved"
    RESERVE = "reserve"  # so: torque beyond capacity, least-squares fallback used
    MAX_ITER = "max_iter"  # solver stopped early; result is the last iterate
    INVALID_INPUT = "invalid_input"  # NaN/inf kinematics, torques or model output; activations are NaN
    SOLVER_FAILED = "solver_failed"  # numerical failure; activations are NaN


@dataclass
class FrameResult:
    """One frame's estimate. ``residual`` = model torque - inverse-dynamics torque (N·m, per coordinate)."""

    activations: np.ndarray
    forces: np.ndarray
    model_torques: np.ndarray
    torques: np.ndarray
    residual: np.ndarray
    status: FrameStatus
    iterations: int
    solve_time_s: float
    phase: float | None = None
    clamped: bool = False  # the pose was slightly outside the pack's fitted range and was clamped into it
    _hess_parts: tuple[np.ndarray, float, np.ndarray] | None = field(default=None, repr=False)
    _equality: np.ndarray | None = field(default=None, repr=False)
    _std: np.ndarray | None = field(default=None, repr=False)
    _bounds: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)

    @property
    def flagged(self) -> bool:
        return self.status is not FrameStatus.SOLVED

    @property
    def at_bound(self) -> np.ndarray:
        a = self.activations
        lb, ub = self._bounds if self._bounds is not None else (0.0, 1.0)
        return (a <= lb + BOUND_TOL) | (a >= ub - BOUND_TOL)

    @property
    def hessian(self) -> np.ndarray | None:
        """Hessian of the frame's objective in the activations, w A~'A~ + diag(d) (``prior``: diag(1/sigma^2))."""
        if self._hess_parts is None:
            return None
        at, w, d = self._hess_parts
        h = w * (at.T @ at)
        h.flat[:: h.shape[0] + 1] += d
        return h

    @property
    def activation_std(self) -> np.ndarray:
        """Laplace std of each activation (0 at a bound; NaN when the frame has no valid optimum). Lazy."""
        if self._std is None:
            if self._hess_parts is None or not np.all(np.isfinite(self.activations)):
                self._std = np.full(self.activations.shape, np.nan)
            else:
                self._std = laplace_std(self.hessian, ~self.at_bound, self._equality)
        return self._std


class FrameEstimator:
    """Streaming estimator: explicit state = the warm PIQP solvers and the flag counters."""

    def __init__(
        self,
        pack: PackLike | str,
        subject: "SubjectProfile | None" = None,
        method: Method | str = Method.PROPOSED,
        *,
        prior: PhasePrior | None = None,
        f_max: np.ndarray | None = None,
        torque_tolerance: float = 0.01,
        hybrid_weight: float = 0.1,
        a_min: float | np.ndarray = 0.0,
        a_max: float | np.ndarray = 1.0,
        backend: Backend | str = Backend.AUTO,
        eps: float = 1e-8,
        max_iter: int = 100,
    ) -> None:
        self.pack = resolve_pack(pack)
        try:
            self.method = Method(method)
        except ValueError:
            raise EstimationError(
                f"unknown method {method!r}; choose one of {', '.join(m.value for m in Method)}"
            ) from None
        self.groups = list(self.pack.groups)
        self.coordinates = list(self.pack.coordinates)
        if subject is not None:
            subject.check_pack(self.pack)
        if f_max is None:
            f_max = subject.f_max if subject is not None else np.asarray(self.pack.f_max_ref, dtype=float)
        self.f_max = np.asarray(f_max, dtype=float).copy()
        if self.f_max.shape != (len(self.groups),) or not np.all(self.f_max > 0):
            raise EstimationError(f"F_max must be {len(self.groups)} positive values, got {self.f_max}")
        self.prior = prior if prior is not None else (subject.prior if subject is not None else None)
        if self.method in (Method.PROPOSED, Method.PRIOR):
            if self.prior is None:
                raise EstimationError(f"method {self.method.value!r} needs a subject profile with a prior")
            if tuple(self.prior.groups) != tuple(self.groups):
                raise EstimationError("the prior's groups differ from the pack's groups")
        if not torque_tolerance > 0 or not hybrid_weight > 0:
            raise EstimationError("torque_tolerance and hybrid_weight must be positive")
        self.torque_tolerance = float(torque_tolerance)
        self.hybrid_weight = float(hybrid_weight)
        self.eps = eps
        self.max_iter = max_iter
        self.flag_counts: dict[str, int] = {}
        self.frames = 0
        n = len(self.groups)
        self._lb = np.broadcast_to(np.asarray(a_min, dtype=float), (n,)).copy()
        self._ub = np.broadcast_to(np.asarray(a_max, dtype=float), (n,)).copy()
        if not (np.all(self._lb >= 0.0) and np.all(self._ub <= 1.0) and np.all(self._lb < self._ub)):
            raise EstimationError(f"activation bounds must satisfy 0 <= a_min < a_max <= 1; got {a_min}, {a_max}")
        try:
            self.backend = resolve_backend(backend, n)
        except ValueError:
            raise EstimationError(f"unknown backend {backend!r}; choose auto, dense or sparse") from None
        self._two = np.full(n, 2.0)
        self._hybrid_d = np.full(n, 2.0 * self.hybrid_weight)
        self._torque_weight = 1.0 / self.torque_tolerance**2
        if self.method is Method.SO:
            self._qp = EqualityQP(n, len(self.coordinates), self._lb, self._ub, self.backend, eps, max_iter)
        else:
            self._qp = self._new_lsq()
        ranges = getattr(self.pack, "coordinate_ranges", None)
        self._ranges = None if ranges is None else np.asarray(ranges, dtype=float).reshape(len(self.coordinates), 2)
        n_c = len(self.coordinates)
        self._lo = self._ranges[:, 0].copy() if self._ranges is not None else np.full(n_c, -np.inf)
        self._hi = self._ranges[:, 1].copy() if self._ranges is not None else np.full(n_c, np.inf)
        self._lo_list, self._hi_list = self._lo.tolist(), self._hi.tolist()
        self._fallback: LeastSquaresQP | None = None
        # ModelPack.frame() gives lengths, moment arms and torques in one (compiled) call; other packs need not have it
        self._fused_frame = getattr(self.pack, "frame", None)
        self._model_error_logged = False

    # -- public -------------------------------------------------------------------------------------------------

    def step(
        self,
        q: np.ndarray,
        qd: np.ndarray | None = None,
        qdd: np.ndarray | None = None,
        hand_load_newton: float = 0.0,
        torques: np.ndarray | None = None,
        phase: float | None = None,
    ) -> FrameResult:
        """Estimate one frame. Never raises on bad numbers: the result is flagged instead."""
        self.frames += 1
        n_c = len(self.coordinates)
        clamped = False
        try:
            q = np.asarray(q, dtype=float)
            if q.shape != (n_c,):
                return self._invalid(np.full(n_c, np.nan), phase)
            # plain floats: a few comparisons on <= 10 numbers cost less than numpy calls; NaN fails every test
            values = q.tolist()
            if not all(lo <= v <= hi for v, lo, hi in zip(values, self._lo_list, self._hi_list)):
                if not all(math.isfinite(v) for v in values):
                    return self._invalid(np.full(n_c, np.nan), phase)
                qc = np.minimum(np.maximum(q, self._lo), self._hi)
                if (np.abs(qc - q) > CLAMP_TOLERANCE).any():
                    return self._invalid(np.full(n_c, np.nan), phase)  # far outside: never extrapolate
                clamped = True
                q = qc
            if torques is None:
                if qd is None or qdd is None:
                    qd = np.zeros(n_c) if qd is None else qd
                    qdd = np.zeros(n_c) if qdd is None else qdd
                if self._fused_frame is not None:  # one model call for moment arms and inverse dynamics
                    _, r, tau = self._fused_frame(q, qd, qdd, hand_load_newton)
                else:
                    tau = np.asarray(self.pack.inverse_dynamics(q, qd, qdd, hand_load_newton), dtype=float)
                    r = np.asarray(self.pack.moment_arms(q), dtype=float)
            else:
                tau = np.asarray(torques, dtype=float)
                r = np.asarray(self.pack.moment_arms(q), dtype=float)
        except Exception as exc:  # the model pack rejected the pose (or failed): the live loop must go on, flagged
            if not self._model_error_logged:  # say it once, with the reason; later frames are counted as invalid_input
                log.warning("model evaluation failed, frame flagged invalid_input: %s: %s", type(exc).__name__, exc)
                self._model_error_logged = True
            return self._invalid(np.full(n_c, np.nan), phase)
        if tau.shape != (n_c,) or r.shape != (n_c, len(self.groups)):
            return self._invalid(np.full(n_c, np.nan), phase)
        # NaN/inf anywhere in tau or R makes the sum non-finite (q was checked above)
        if not math.isfinite(float(tau.sum()) + float(r.sum())):
            return self._invalid(tau, phase)
        if phase is not None and not math.isfinite(phase):
            phase = None
        result = self._solve(r * self.f_max, tau, phase)
        if clamped:
            result.clamped = True
            self._count_key("out_of_range_clamped")
        return result

    def reset_counts(self) -> None:
        self.flag_counts.clear()
        self.frames = 0

    # -- internals ----------------------------------------------------------------------------------------------

    def _solve(self, a_mat: np.ndarray, tau: np.ndarray, phase: float | None) -> FrameResult:
        scale = np.abs(a_mat).sum(axis=1)
        np.maximum(scale, MIN_TORQUE_SCALE, out=scale)
        at = a_mat / scale[:, None]
        tt = tau / scale
        method = self.method
        if method is Method.PRIOR:
            mu, prec = self.prior.mean_precision(phase)
            x = np.clip(mu, self._lb, self._ub)
            # curvature of the prior alone: the std reported is the prior's sigma
            return self._result(x, a_mat, tau, FrameStatus.SOLVED, 0, 0.0, phase, (at, 0.0, prec), None)
        if method is Method.SO:
            if self._so_certainly_infeasible(at, tt):
                return self._so_fallback(a_mat, tau, at, tt, phase)
            status, x, it, dt = self._qp.solve(at, tt)
            if status in (piqp.PIQP_PRIMAL_INFEASIBLE, piqp.PIQP_DUAL_INFEASIBLE):
                return self._so_fallback(a_mat, tau, at, tt, phase)
            parts = (at, 0.0, self._two)
            return self._finish(status, x, it, dt, a_mat, tau, phase, parts, at)
        if method is Method.HYBRID:
            w, d, c_a = 2.0, self._hybrid_d, None
        else:
            mu, d = self.prior.mean_precision(phase)
            w, c_a = self._torque_weight, -(d * mu)
        status, x, it, dt = self._qp.solve(at, tt, w, d, c_a)
        return self._finish(status, x, it, dt, a_mat, tau, phase, (at, w, d), None)

    def _finish(self, status, x, it, dt, a_mat, tau, phase, hess_parts, equality) -> FrameResult:
        if status == piqp.PIQP_SOLVED:
            fs = FrameStatus.SOLVED
        elif status == piqp.PIQP_MAX_ITER_REACHED and np.isfinite(x.sum()):
            fs = FrameStatus.MAX_ITER
        else:
            fs = FrameStatus.SOLVER_FAILED
            x = np.full(len(self.groups), np.nan)
        if fs is not FrameStatus.SOLVER_FAILED:
            x = np.minimum(np.maximum(x, self._lb), self._ub)  # interior-point iterates may sit 1e-9 outside
        return self._result(x, a_mat, tau, fs, it, dt, phase, hess_parts, equality)

    def _so_certainly_infeasible(self, at: np.ndarray, tt: np.ndarray) -> bool:
        """Cheap necessary condition: each coordinate's torque must lie within its muscles' range (a in bounds)."""
        pos, neg = np.clip(at, 0.0, None), np.clip(at, None, 0.0)
        hi = pos @ self._ub + neg @ self._lb
        lo = pos @ self._lb + neg @ self._ub
        return bool(np.any(tt > hi + 1e-9) or np.any(tt < lo - 1e-9))

    def _so_fallback(self, a_mat, tau, at, tt, phase) -> FrameResult:
        """min sum a^2 + RESERVE_WEIGHT |A~ a - t~|^2: the least-squares reserve solution, flagged."""
        if self._fallback is None:
            self._fallback = self._new_lsq()
        w = 2.0 * RESERVE_WEIGHT
        status, x, it, dt = self._fallback.solve(at, tt, w, self._two, None)
        result = self._finish(status, x, it, dt, a_mat, tau, phase, (at, w, self._two), None)
        if result.status is FrameStatus.SOLVED:
            result.status = FrameStatus.RESERVE
            self._count(FrameStatus.RESERVE)
        return result

    def _new_lsq(self) -> LeastSquaresQP:
        return LeastSquaresQP(len(self.groups), len(self.coordinates), self._lb, self._ub, self.backend, self.eps,
                              self.max_iter)

    def _result(self, x, a_mat, tau, status, it, dt, phase, hess_parts, equality) -> FrameResult:
        forces = self.f_max * x
        model = a_mat @ x
        result = FrameResult(
            activations=x,
            forces=forces,
            model_torques=model,
            torques=tau,
            residual=model - tau,
            status=status,
            iterations=it,
            solve_time_s=dt,
            phase=phase,
            _hess_parts=hess_parts,
            _equality=equality,
            _bounds=(self._lb, self._ub),
        )
        if status is not FrameStatus.SOLVED and status is not FrameStatus.RESERVE:
            self._count(status)
        return result

    def _invalid(self, tau: np.ndarray, phase: float | None) -> FrameResult:
        n = len(self.groups)
        nan = np.full(n, np.nan)
        n_c = len(self.coordinates)
        result = FrameResult(
            activations=nan,
            forces=nan.copy(),
            model_torques=np.full(n_c, np.nan),
            torques=np.asarray(tau, dtype=float) if np.shape(tau) == (n_c,) else np.full(n_c, np.nan),
            residual=np.full(n_c, np.nan),
            status=FrameStatus.INVALID_INPUT,
            iterations=0,
            solve_time_s=0.0,
            phase=phase,
        )
        self._count(FrameStatus.INVALID_INPUT)
        return result

    def _count(self, status: FrameStatus) -> None:
        self._count_key(status.value)

    def _count_key(self, key: str) -> None:
        first = key not in self.flag_counts
        self.flag_counts[key] = self.flag_counts.get(key, 0) + 1
        if first:
            log.warning("frame %d flagged %r (further occurrences are counted in flag_counts)", self.frames, key)

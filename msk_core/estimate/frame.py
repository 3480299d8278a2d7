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
- ``assisted``: ``proposed`` with the frame's own measured EMG: for every group whose normalised envelope e_g is
  given (``step(emg=...)``, finite), the prior term is replaced by the calibration's EMG term N(e_g, sigma_e^2),
  sigma_e^2 = emg_std^2 + (emg_relative_std e_g)^2 (:class:`msk_core.estimate.calibrate.CalibrationSettings`, which
  also gives the calibrated prior no weight where a group's EMG is known); the phase prior for the other groups.
  Always one warm PIQP per frame (no active-set hot start: the EMG changes the prior every frame).

One PIQP solver per estimator (dense, or sparse from 40 groups up: :mod:`msk_core.estimate.qp`) is set up on the
first frame and then only ``update()``-d with the new matrices, so its workspace and preconditioner
(``preconditioner_reuse_on_update``) are reused frame after frame.
(PIQP is an interior-point method: it takes no primal starting point, so "warm" means the reused workspace and
scaling.) For every method but the prior alone each frame is first tried by a compiled primal active-set method
hot-started from the previous frame's solution and working set (:mod:`msk_core.estimate.active_set`; ``assisted``
with the live EMG folded into its prior's row of the frame; ``so`` by its
equality-constrained kernel, whose frames PIQP finds infeasible still end in the reserve fallback); its answer is
used only when the KKT conditions certify it as the optimum (usually after one m x m solve, a few µs), and PIQP
solves the frame otherwise (after ``hot_start_max_changes`` working-set changes; ``hot_start=False``: PIQP always).
``FrameResult.solver`` says which one answered, ``FrameEstimator.solver_counts`` how often.
``step()`` never raises on bad data: NaN
input, infeasible torques or solver failures come back as a flagged :class:`FrameResult` and are counted in
:attr:`FrameEstimator.flag_counts` (a warning is logged on the first occurrence of each flag). Poses up to
``CLAMP_TOLERANCE`` (5 deg) outside the pack's fitted ranges are clamped into them (``clamped``, counted as
``out_of_range_clamped``); further out the frame is ``invalid_input`` rather than an extrapolated number.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from enum import Enum
from typing import TYPE_CHECKING

import numpy as np
import piqp

from msk_core.errors import EstimationError
from msk_core.estimate import active_set
from msk_core.estimate.effects import ModelEffects
from msk_core.estimate.laplace import laplace_std
from msk_core.estimate.pack import (
    MusclePackLike,
    PackLike,
    PosedPackLike,
    clamp_to_ranges,
    fitted_ranges,
    resolve_pack,
)
from msk_core.estimate.prior import MIN_STD, NO_EMG_STD, LoadScale, PhasePrior
from msk_core.estimate.qp import Backend, EqualityQP, LeastSquaresQP, resolve_backend

if TYPE_CHECKING:
    from msk_core.estimate.profile import SubjectProfile

log = logging.getLogger(__name__)

MIN_TORQUE_SCALE = 1.0  # N·m; floor of the per-coordinate residual scale (coordinates almost no muscle crosses)
RESERVE_WEIGHT = 1.0e4  # weight of the scaled residual in the `so` reserve fallback
# assisted: a measured synergist whose pooled prior mean is below this cannot set another group's level from its envelope
MIN_SYNERGIST_LEVEL = 1.0e-3
BOUND_TOL = active_set.BOUND_TOL  # an activation this close to a bound counts as at it (Laplace free set)


class Method(str, Enum):
    PROPOSED = "proposed"
    SO = "so"
    HYBRID = "hybrid"
    PRIOR = "prior"
    ASSISTED = "assisted"


#: The methods whose objective is a negative log-density of activation (a prior, EMG and torque noise with stated
#: spreads), so that its Laplace std is an uncertainty: published with their frames. ``so``'s Σa² and ``hybrid``'s
#: weights are no such density (their "std" is 1/√2 ≈ 0.71 for every free group, which a new user's dashboard showed
#: as ±70 % bars); :attr:`FrameResult.activation_std` still gives it for every method.
UNCERTAIN_METHODS = frozenset({Method.PROPOSED, Method.ASSISTED, Method.PRIOR})
#: The methods that follow the torque softly (a weighted residual, never a reserve): a frame whose torque is beyond
#: the muscles' capacity is flagged ``reserve`` all the same.
SOFT_TORQUE_METHODS = frozenset({Method.PROPOSED, Method.ASSISTED, Method.HYBRID})

#: why a frame is ``invalid_input`` (FrameResult.reason; the estimator's summary counts them)
INVALID_REASONS = (
    "q wrong shape",
    "q non-finite",
    "q out of range",
    "model error",
    "torques wrong shape",
    "torques or moment arms non-finite",
)


class FrameStatus(str, Enum):
    SOLVED = "solved"
    # torque beyond the muscles' capacity at the pose: so uses its least-squares fallback; the other methods keep their
    # solution, the torque left unexplained said (they reported "solved" with 99 % of a torque unexplained)
    RESERVE = "reserve"
    MAX_ITER = "max_iter"  # solver stopped early; result is the last iterate
    INVALID_INPUT = "invalid_input"  # NaN/inf kinematics, torques or model output; activations are NaN
    SOLVER_FAILED = "solver_failed"  # numerical failure; activations are NaN


@dataclass(slots=True)
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
    solver: str = "piqp"  # "active_set" (hot start, KKT-certified), "piqp" or "none" (prior / invalid input)
    reason: str = ""  # why the input was invalid (INVALID_REASONS), "" otherwise
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
            hessian = self.hessian
            if hessian is None or not np.all(np.isfinite(self.activations)):
                self._std = np.full(self.activations.shape, np.nan)
            else:
                self._std = laplace_std(hessian, ~self.at_bound, self._equality)
        return self._std


class FrameEstimator:
    """Streaming estimator: explicit state = the warm PIQP solvers and the flag counters."""

    def __init__(
        self,
        pack: PackLike | str,
        subject: SubjectProfile | None = None,
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
        hot_start: bool = True,
        hot_start_max_changes: int | None = None,
        emg_std: float = 0.05,
        emg_relative_std: float = 0.1,
        live_synergists: bool = True,
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
        self._init_effects_and_strength(subject, f_max)
        self.live_synergists = bool(live_synergists)
        self._init_prior(subject, prior)
        if not torque_tolerance > 0 or not hybrid_weight > 0:
            raise EstimationError("torque_tolerance and hybrid_weight must be positive")
        if not emg_std > 0 or not emg_relative_std >= 0:
            raise EstimationError("emg_std must be positive and emg_relative_std non-negative")
        self.emg_std, self.emg_relative_std = float(emg_std), float(emg_relative_std)
        self._emg: np.ndarray | None = None
        self.torque_tolerance = float(torque_tolerance)
        self.hybrid_weight = float(hybrid_weight)
        self.eps = eps
        self.max_iter = max_iter
        self.flag_counts: dict[str, int] = {}
        self.frames = 0
        self._init_solvers(a_min, a_max, backend, hot_start, hot_start_max_changes)
        # ModelPack.frame() gives lengths, moment arms and torques in one (compiled) call; other packs need not have it
        self._fused_frame = self.pack.frame if isinstance(self.pack, MusclePackLike) else None
        self._model_error_logged = False

    def _init_effects_and_strength(self, subject: SubjectProfile | None, f_max: np.ndarray | None) -> None:
        """The profile's model effects and the F_max the estimate uses (the argument, else the profile's times the
        effects' strength gain, else the pack's reference)."""
        # the profile's model effects (msk_core.estimate.effects): force scales, torque offsets, a prior delay
        self.effects: ModelEffects | None = None
        if subject is not None and subject.effects:
            self.effects = ModelEffects.from_dict(subject.effects, self.groups, self.coordinates).bind(self.pack)
        # the pack whose muscle lengths the effects read every frame (bind checked that it has them); None: not read
        self._lengths_pack: MusclePackLike | None = None
        if self.effects is not None and self.effects.needs_lengths and isinstance(self.pack, MusclePackLike):
            self._lengths_pack = self.pack
        self._f_max_profile = None if subject is None else np.asarray(subject.f_max, dtype=float)
        if f_max is None:
            f_max = subject.f_max if subject is not None else np.asarray(self.pack.f_max_ref, dtype=float)
            if self.effects is not None:
                f_max = np.asarray(f_max, dtype=float) * self.effects.strength_gain
        self.f_max = np.asarray(f_max, dtype=float).copy()
        if self.f_max.shape != (len(self.groups),) or not np.all(self.f_max > 0):
            raise EstimationError(f"F_max must be {len(self.groups)} positive values, got {self.f_max}")

    def _init_prior(self, subject: SubjectProfile | None, prior: PhasePrior | None) -> None:
        """The prior (the argument, else the profile's, unmixed by its effects), checked against the method."""
        self.prior = prior if prior is not None else (subject.prior if subject is not None else None)
        # the prior at another load than its training's: scaled by the torque the lift needs (prior.LoadScale)
        self._load_scale: LoadScale | None = None
        self._scale: np.ndarray | None = None  # this frame's load scale per group; None: the prior as learned
        if self.effects is not None and prior is None:
            self.prior = self.effects.unmix_prior(self.prior)
        self._phase_history = None if self.effects is None else self.effects.new_phase_history()
        if self.method in (Method.PROPOSED, Method.PRIOR, Method.ASSISTED):
            if self.prior is None:
                raise EstimationError(f"method {self.method.value!r} needs a subject profile with a prior")
            if tuple(self.prior.groups) != tuple(self.groups):
                raise EstimationError("the prior's groups differ from the pack's groups")
            if self.prior.torque is not None:
                if self.prior.torque.shape[1] != len(self.coordinates):
                    raise EstimationError(
                        f"the prior's training torque has {self.prior.torque.shape[1]} coordinates, the pack "
                        f"{len(self.coordinates)}"
                    )
                self._load_scale = LoadScale(self.prior)
        self._init_live_synergists(subject)

    def _init_live_synergists(self, subject: SubjectProfile | None) -> None:
        """``assisted``: for each group without EMG, the measured synergist whose live envelope informs it (index,
        -1: none), the gain that brings that envelope to the group's own prior level (ratio of their pooled prior
        means) and the weight of that scaled envelope in the group's prior mean (the rest: its phase prior; the
        prior's spread is kept, so the torque term moves the group as much as before). A group whose prior *is* its
        synergist's (source ``synergist:<group>``) takes the live envelope (weight 1). Any other group (the profile's
        moment-arm ``synergists``) weighs the two hypotheses by the errors each showed on the measured groups:
        w = e_p^2 / (e_p^2 + e_s^2), e_p the minimal-effort error (``min_effort_error_rms``; the wide default's
        ``NO_EMG_STD`` for a default prior), e_s the error of "a synergist's envelope at the group's own level": how
        well this source stood for its own measured synergists (``synergist_error_by_source``), else between all the
        measured synergist pairs (``synergist_error_rms``); without either (no measured pair to check it on) the
        group is left alone."""
        n = len(self.groups)
        self._synergist_of = np.full(n, -1)
        self._synergist_gain = np.zeros(n)
        self._synergist_weight = np.zeros(n)
        if self.prior is None or not self.live_synergists:
            return
        calibration = subject.calibration if subject is not None else {}
        named = {g: (h, False) for g, h in (calibration.get("synergists") or {}).items()}
        sources = self.prior.sources or ("",) * n
        for j, src in enumerate(sources):
            if src.startswith("synergist:"):
                named[self.groups[j]] = (src.removeprefix("synergist:"), True)
        pooled_err = float(calibration.get("synergist_error_rms") or np.nan)
        by_source = calibration.get("synergist_error_by_source") or {}
        me_err = float(calibration.get("min_effort_error_rms") or np.nan)
        mu, _ = self.prior.pooled()
        for g, (h, copied) in named.items():
            if g not in self.groups or h not in self.groups:
                continue
            j, k = self.groups.index(g), self.groups.index(h)
            prior_err = me_err if sources[j] == "min_effort" else NO_EMG_STD
            syn_err = float(by_source.get(h, pooled_err))
            weight = 1.0 if copied else prior_err**2 / (prior_err**2 + syn_err**2)
            if self.prior.has_emg[k] and not self.prior.has_emg[j] and mu[k] > MIN_SYNERGIST_LEVEL and weight > 0:
                self._synergist_of[j], self._synergist_gain[j], self._synergist_weight[j] = k, mu[j] / mu[k], weight

    def _init_solvers(
        self,
        a_min: float | np.ndarray,
        a_max: float | np.ndarray,
        backend: Backend | str,
        hot_start: bool,
        hot_start_max_changes: int | None,
    ) -> None:
        """Activation bounds, the warm QP, the pack's fitted ranges, the hot-start state and the prior table."""
        n = len(self.groups)
        self._lb = np.broadcast_to(np.asarray(a_min, dtype=float), (n,)).copy()
        self._ub = np.broadcast_to(np.asarray(a_max, dtype=float), (n,)).copy()
        if not (np.all(self._lb >= 0.0) and np.all(self._ub <= 1.0) and np.all(self._lb < self._ub)):
            raise EstimationError(f"activation bounds must satisfy 0 <= a_min < a_max <= 1; got {a_min}, {a_max}")
        # what a coordinate's muscles can make, per N·m of moment arm: centre and half-width of each group's force range
        self._force_centre = self.f_max * (self._lb + self._ub) / 2
        self._force_half = self.f_max * (self._ub - self._lb) / 2
        try:
            self.backend = resolve_backend(backend, n)
        except ValueError:
            raise EstimationError(f"unknown backend {backend!r}; choose auto, dense or sparse") from None
        self._two = np.full(n, 2.0)
        self._hybrid_d = np.full(n, 2.0 * self.hybrid_weight)
        self._torque_weight = 1.0 / self.torque_tolerance**2
        # the method's warm QP: SO's equality-constrained one, the others' least-squares one
        self._qp: EqualityQP | LeastSquaresQP
        if self.method is Method.SO:
            self._qp = EqualityQP(n, len(self.coordinates), self._lb, self._ub, self.backend, self.eps, self.max_iter)
        else:
            self._qp = self._new_lsq()
        self._fitted = fitted_ranges(self.pack)
        n_c = len(self.coordinates)
        self._lo = self._fitted[0] if self._fitted is not None else np.full(n_c, -np.inf)
        self._hi = self._fitted[1] if self._fitted is not None else np.full(n_c, np.inf)
        self._lo_list, self._hi_list = self._lo.tolist(), self._hi.tolist()
        self._fallback: LeastSquaresQP | None = None
        # hot start: the active-set method's cost per working-set change is O(m^2 G) (Woodbury), so it pays at any size
        self.hot_start = bool(hot_start)
        self._hot_x, self._hot_state = active_set.new_state(n)
        # working-set changes allowed before the frame goes to PIQP (a cold start needs up to ~G)
        self._hot_max_changes = 2 * n + 10 if hot_start_max_changes is None else int(hot_start_max_changes)
        # the trailing arguments of both compiled solves: bounds, residual-scale floor and the hot state (updated in
        # place, so the tuple stays valid)
        self._hot_tail = (self._lb, self._ub, MIN_TORQUE_SCALE, self._hot_x, self._hot_state, self._hot_max_changes)
        # prior as one table for the compiled solve: phase bins, then the pooled row, then the rest row (hybrid: one
        # row, mean 0, precision 2 * hybrid_weight)
        if self.method in (Method.PROPOSED, Method.ASSISTED):
            self._prior_mean, self._prior_prec = self._required_prior.table()
        else:
            self._prior_mean, self._prior_prec = np.zeros((1, n)), self._hybrid_d[None, :].copy()
        self.solver_counts: dict[str, int] = {"active_set": 0, "piqp": 0}

    # -- public -------------------------------------------------------------------------------------------------

    def step(
        self,
        q: np.ndarray,
        qd: np.ndarray | None = None,
        qdd: np.ndarray | None = None,
        hand_load_newton: float = 0.0,
        torques: np.ndarray | None = None,
        phase: float | None = None,
        emg: np.ndarray | None = None,
    ) -> FrameResult:
        """Estimate one frame. Never raises on bad numbers: the result is flagged instead.

        ``emg``: normalised envelope per group (NaN where not measured), used by ``assisted`` only.
        ``hand_load_newton``: the load declared for this frame, also when ``torques`` are given (what the prior's
        load scale compares with the prior's training load)."""
        self.frames += 1
        if self._load_scale is not None:
            self._load_scale.set_load(float(hand_load_newton))
        self._emg = emg
        n_c = len(self.coordinates)
        clamped = False
        try:
            q = np.asarray(q, dtype=float)
            if q.shape != (n_c,):
                return self._invalid(np.full(n_c, np.nan), phase, "q wrong shape")
            # plain floats: a few comparisons on <= 10 numbers cost less than numpy calls; NaN fails every test
            values = q.tolist()
            if not all(lo <= v <= hi for v, lo, hi in zip(values, self._lo_list, self._hi_list)):
                q, usable = clamp_to_ranges(q, self._fitted)
                if not usable:
                    # non-finite, or far outside: never extrapolate
                    why = "q out of range" if np.all(np.isfinite(q)) else "q non-finite"
                    return self._invalid(np.full(n_c, np.nan), phase, why)
                clamped = True
            lengths = None
            if self.effects is not None:
                qd = np.zeros(n_c) if qd is None else np.asarray(qd, dtype=float)
                qdd = np.zeros(n_c) if qdd is None else np.asarray(qdd, dtype=float)
                if torques is None:  # the external load as the effects say it really was
                    hand_load_newton = hand_load_newton * self.effects.load_ratio
            if torques is None:
                if qd is None or qdd is None:
                    qd = np.zeros(n_c) if qd is None else qd
                    qdd = np.zeros(n_c) if qdd is None else qdd
                if self._fused_frame is not None:  # one model call for moment arms and inverse dynamics
                    lengths, r, tau = self._fused_frame(q, qd, qdd, hand_load_newton)
                else:
                    tau = np.asarray(self.pack.inverse_dynamics(q, qd, qdd, hand_load_newton), dtype=float)
                    lengths, r = self._lengths_and_arms(q)
            else:
                tau = np.asarray(torques, dtype=float)
                lengths, r = self._lengths_and_arms(q)
                if (
                    self.effects is not None  # which set qd and qdd above
                    and qd is not None
                    and qdd is not None
                    and self.effects.load_ratio != 1.0
                    and hand_load_newton
                ):
                    # measured torques hold the reported load: add the rest of the true load's moment
                    load = np.asarray(
                        self.pack.inverse_dynamics(q, qd, qdd, hand_load_newton), dtype=float
                    ) - np.asarray(self.pack.inverse_dynamics(q, qd, qdd, 0.0), dtype=float)
                    tau = tau + (self.effects.load_ratio - 1.0) * load
            # the load scale compares the torque with the training's at the training's phase: before the effects
            self._update_load_scale(r, tau, phase)
            if self.effects is not None:
                r, tau, phase = self._apply_effects(q, qd, lengths, r, tau, phase)
        except Exception as exc:  # the model pack rejected the pose (or failed): the live loop must go on, flagged
            if not self._model_error_logged:  # say it once, with the reason; later frames are counted as invalid_input
                log.warning("model evaluation failed, frame flagged invalid_input: %s: %s", type(exc).__name__, exc)
                self._model_error_logged = True
            return self._invalid(np.full(n_c, np.nan), phase, "model error")
        result = self._checked_solve(r, tau, phase, emg)
        if clamped:
            result.clamped = True
            self._count_key("out_of_range_clamped")
        return result

    def solve(
        self,
        r: np.ndarray,
        tau: np.ndarray,
        phase: float | None = None,
        emg: np.ndarray | None = None,
        load_newton: float | None = None,
    ) -> FrameResult:
        """Estimate one frame from its moment arms ``r`` (n_c, G) and torques ``tau`` (n_c,) already at hand (what
        :meth:`step` does once the pack has given them; offline work that has the trial's moment arms reuses them).
        ``emg`` as in :meth:`step`; ``load_newton``: the frame's declared load (None: as before, :meth:`step`'s
        ``hand_load_newton``). Flags instead of raising, as :meth:`step`."""
        if load_newton is not None and self._load_scale is not None:
            self._load_scale.set_load(float(load_newton))
        self._update_load_scale(r, tau, phase)
        return self._checked_solve(r, tau, phase, emg)

    def _update_load_scale(self, r: np.ndarray, tau: np.ndarray, phase: float | None) -> None:
        """This frame's load scale (None: the prior as learned) from its moment arms, torques and phase; a frame
        with unusable numbers neither moves the average nor is scaled."""
        self._scale = None
        if self._load_scale is None or not self._load_scale.active:  # the prior's own load: nothing to do per frame
            return
        r, tau = np.asarray(r, dtype=float), np.asarray(tau, dtype=float)
        usable = tau.shape == (len(self.coordinates),) and r.shape == (len(self.coordinates), len(self.groups))
        if usable and math.isfinite(float(tau.sum()) + float(r.sum())) and phase is not None and math.isfinite(phase):
            self._scale = self._load_scale.update(r, tau, phase)

    def _checked_solve(
        self, r: np.ndarray, tau: np.ndarray, phase: float | None, emg: np.ndarray | None
    ) -> FrameResult:
        """:meth:`solve` once the load scale is known: the frame's numbers checked, then solved."""
        self._emg = emg
        n_c = len(self.coordinates)
        if tau.shape != (n_c,) or r.shape != (n_c, len(self.groups)):
            return self._invalid(np.full(n_c, np.nan), phase, "torques wrong shape")
        # NaN/inf anywhere in tau or R makes the sum non-finite
        if not math.isfinite(float(tau.sum()) + float(r.sum())):
            return self._invalid(tau, phase, "torques or moment arms non-finite")
        if phase is not None and not math.isfinite(phase):
            phase = None
        return self._solve(r, tau, phase)

    def warm_up(self) -> None:
        """One throw-away frame at the pack's reference pose (mid-range when it has none), at rest and unloaded: the
        compiled kernels are loaded (or compiled, on a fresh install) and the solvers set up before the first live
        frame, which would otherwise be late by that much. Counters and the hot start are reset afterwards."""
        n_c = len(self.coordinates)
        pose = self.pack.reference_pose if isinstance(self.pack, PosedPackLike) else None
        if pose is None:
            pose = np.zeros(n_c) if self._fitted is None else (self._fitted[0] + self._fitted[1]) / 2
        self.step(np.asarray(pose, dtype=float), np.zeros(n_c), np.zeros(n_c), 0.0, phase=None)
        self.reset_counts()
        self.new_recording()

    def new_recording(self) -> None:
        """The next frames are another recording's (offline: the next trial): what the estimator carried over frames
        starts again (the hot start, the load scale's average, the delay's look-back at the phase); counters stay."""
        self._reset_hot_start()
        if self._load_scale is not None:
            self._load_scale.set_load(None)
        if self._phase_history is not None:
            self._phase_history.clear()

    def reset_counts(self) -> None:
        self.flag_counts.clear()
        self.solver_counts = {"active_set": 0, "piqp": 0}
        self.frames = 0

    # -- internals ----------------------------------------------------------------------------------------------

    def _apply_effects(self, q, qd, lengths, r, tau, phase):
        """Moment arms scaled by the per-frame force factors, torque minus the known offsets, the prior's phase
        delayed (the QP itself is unchanged)."""
        eff = self.effects
        r = np.asarray(r, dtype=float)
        scale = eff.force_scale(lengths, r, qd)
        offset = eff.torque_offset(q, qd, lengths, r, self._f_max_profile)
        if offset is not None:
            tau = np.asarray(tau, dtype=float) - offset
        if scale is not None:
            r = r * scale[None, :]
        if eff._arm_scale is not None:
            r = r * eff._arm_scale
        if self._phase_history is not None:  # EMG (and the prior learned from it) leads the force: look back
            self._phase_history.append(phase)
            phase = self._phase_history[0]
        return r, tau, phase

    def _solve(self, r: np.ndarray, tau: np.ndarray, phase: float | None) -> FrameResult:
        result = self._solve_method(r, tau, phase)
        if self.method in SOFT_TORQUE_METHODS and result.status is FrameStatus.SOLVED and self._beyond_capacity(r, tau):
            result.status = FrameStatus.RESERVE
            self._count(FrameStatus.RESERVE)
        return result

    def _solve_method(self, r: np.ndarray, tau: np.ndarray, phase: float | None) -> FrameResult:
        method = self.method
        if self.hot_start and method is not Method.PRIOR:
            hot = self._hot_solve(r, tau, phase)
            if hot is not None:
                return hot
        a_mat = r * self.f_max
        scale = np.abs(a_mat).sum(axis=1)
        np.maximum(scale, MIN_TORQUE_SCALE, out=scale)
        at = a_mat / scale[:, None]
        tt = tau / scale
        if method is Method.PRIOR:
            mu, prec = self._prior_terms(phase)
            x = np.clip(mu, self._lb, self._ub)
            # curvature of the prior alone: the std reported is the prior's sigma
            result = self._result(x, a_mat, tau, FrameStatus.SOLVED, 0, 0.0, phase, (at, 0.0, prec), None)
            result.solver = "none"
            return result
        if method is Method.SO:
            if self._beyond_capacity(r, tau):
                return self._so_fallback(a_mat, tau, at, tt, phase)
            assert isinstance(self._qp, EqualityQP)  # SO's, made with the method
            status, x, it, dt = self._qp.solve(at, tt)
            if status in (piqp.PIQP_PRIMAL_INFEASIBLE, piqp.PIQP_DUAL_INFEASIBLE):
                return self._so_fallback(a_mat, tau, at, tt, phase)
            result = self._finish(status, x, it, dt, a_mat, tau, phase, (at, 0.0, self._two), at)
            self._after_piqp(result)
            return result
        if method is Method.HYBRID:
            w, d, c_a = 2.0, self._hybrid_d, None
        else:
            mu, d = self._prior_terms(phase)
            if method is Method.ASSISTED and self._emg is not None:
                mu, d = self._emg_term(mu, d)
            w, c_a = self._torque_weight, -(d * mu)
        assert isinstance(self._qp, LeastSquaresQP)  # the other methods', made with the method
        status, x, it, dt = self._qp.solve(at, tt, w, d, c_a)
        result = self._finish(status, x, it, dt, a_mat, tau, phase, (at, w, d), None)
        self._after_piqp(result)
        return result

    def _prior_terms(self, phase: float | None) -> tuple[np.ndarray, np.ndarray]:
        """The prior's (mean, precision) at ``phase``, at this frame's load: when scaled, the mean's part above the
        rest level times s (the tone at rest does not grow with the load) and the spread times s."""
        prior = self._required_prior
        mu, prec = prior.mean_precision(phase)
        if self._scale is None:
            return mu, prec
        base = np.minimum(mu, prior.rest_mean) if prior.rest_mean is not None else 0.0
        # a spread scaled down keeps the prior's floor (MIN_STD: no bin becomes a hard constraint)
        return base + self._scale * (mu - base), np.minimum(prec / self._scale**2, np.maximum(prec, 1.0 / MIN_STD**2))

    @property
    def load_scale(self) -> dict | None:
        """What the prior's load scale did so far (:meth:`LoadScale.summary`); None when it scaled no frame."""
        return None if self._load_scale is None else self._load_scale.summary()

    @property
    def _required_prior(self) -> PhasePrior:
        """The prior of a method that reads one (construction refused those methods without it)."""
        if self.prior is None:
            raise EstimationError(f"method {self.method.value!r} needs a subject profile with a prior")
        return self.prior

    def _lengths_and_arms(self, q: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
        """(muscle-tendon lengths, or None when the effects do not read them; moment arms) at q."""
        if self._lengths_pack is not None:
            lengths, r = self._lengths_pack.lengths_and_moment_arms(q)
            return lengths, np.asarray(r, dtype=float)
        return None, np.asarray(self.pack.moment_arms(q), dtype=float)

    def _emg_term(self, mu: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Prior (mean, precision) with the measured groups' N(e_g, sigma_e^2) in place of the phase prior."""
        e = np.asarray(self._emg, dtype=float)
        measured = np.isfinite(e)
        if e.shape != mu.shape or not measured.any():
            return mu, d
        mu, d = mu.copy(), d.copy()
        # a group without its own envelope with a measured synergist: that synergist's live envelope, brought to the
        # group's own prior level (same drive, its own gain), weighed into its prior mean; the prior's spread kept
        src = self._synergist_of
        lent = (src >= 0) & ~measured
        if lent.any():
            live = e[src[lent]]
            take = np.isfinite(live)
            idx = np.flatnonzero(lent)[take]
            w = self._synergist_weight[idx]
            mu[idx] = w * live[take] * self._synergist_gain[idx] + (1.0 - w) * mu[idx]
        em = e[measured]
        mu[measured] = em
        d[measured] = 1.0 / (self.emg_std**2 + (self.emg_relative_std * em) ** 2)
        return mu, d

    def _hot_solve(self, r, tau, phase) -> FrameResult | None:
        """The frame from the hot-started active-set method when it certifies the optimum, else None (-> PIQP)."""
        t0 = time.perf_counter()
        if self.method is Method.SO:
            code, changes, out, torques = active_set.solve_min_norm_eq(r, self.f_max, tau, *self._hot_tail)
            w, equality = 0.0, True
        else:
            code, changes, out, torques, w = self._hot_box_lsq(r, tau, phase)
            equality = False
        dt = time.perf_counter() - t0
        if code != active_set.CERTIFIED:
            return None
        self.solver_counts["active_set"] += 1
        m = tau.shape[0]
        return FrameResult(
            activations=out[m],
            forces=out[m + 1],
            model_torques=torques[0],
            torques=tau,
            residual=torques[1],
            status=FrameStatus.SOLVED,
            iterations=changes + 1,  # equality-constrained solves
            solve_time_s=dt,
            phase=phase,
            solver="active_set",
            _hess_parts=(out[:m], w, out[m + 2]),
            _equality=out[:m] if equality else None,
            _std=out[m + 3] if not math.isnan(out[m + 3, 0]) else None,  # the kernel's, else computed when read
            _bounds=(self._lb, self._ub),
        )

    def _hot_box_lsq(self, r, tau, phase):
        """:func:`active_set.solve_box_lsq` on the frame of ``proposed``, ``assisted`` or ``hybrid``: (code, changes,
        out, torques, w)."""
        mean, prec = self._prior_mean, self._prior_prec
        if self.method is Method.HYBRID:
            w, row0, row1, frac = 2.0, 0, 0, 0.0
        elif (self.method is Method.ASSISTED and self._emg is not None) or self._scale is not None:
            # the prior with the live EMG in it, or at another load: one row
            w, row0, row1, frac = self._torque_weight, 0, 0, 0.0
            mu, d = self._prior_terms(phase)
            if self.method is Method.ASSISTED and self._emg is not None:
                mu, d = self._emg_term(mu, d)
            mean, prec = mu[None, :], d[None, :]
        else:
            w = self._torque_weight
            row0, row1, frac = self._required_prior.rows(phase)
        code, changes, out, torques = active_set.solve_box_lsq(
            r, self.f_max, tau, w, mean, prec, row0, row1, frac, *self._hot_tail, True
        )
        return code, changes, out, torques, w

    def _after_piqp(self, result: FrameResult) -> None:
        """Count a PIQP frame and seed the next hot start with its solution (or restart from scratch)."""
        self.solver_counts["piqp"] += 1
        if self.hot_start:
            if np.all(np.isfinite(result.activations)):
                self._hot_x[:] = result.activations
                active_set.seed_state(self._hot_x, self._lb, self._ub, BOUND_TOL, self._hot_state)
            else:
                self._reset_hot_start()

    def _reset_hot_start(self) -> None:
        """Next frame starts cold: everything free at 0 (the state :func:`active_set.new_state` gives)."""
        self._hot_x[:], self._hot_state[:] = 0.0, active_set.FREE

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

    def _beyond_capacity(self, r: np.ndarray, tau: np.ndarray) -> bool:
        """Some coordinate's torque ``tau`` lies outside what its muscles (moment arms ``r``) can make with activations
        in bounds: so's certain infeasibility, the others' reserve flag. The range is centre +- half-width (two
        products per frame, on every frame of every method: the clipped matrices of the first version cost 33 us);
        the tolerance is 1e-9 of the coordinate's residual scale, as on so's scaled rows."""
        arms = np.abs(r)
        margin = 1e-9 * np.maximum(arms @ self.f_max, MIN_TORQUE_SCALE)
        return bool(np.any(np.abs(tau - r @ self._force_centre) > arms @ self._force_half + margin))

    def _so_fallback(self, a_mat, tau, at, tt, phase) -> FrameResult:
        """min sum a^2 + RESERVE_WEIGHT |A~ a - t~|^2: the least-squares reserve solution, flagged."""
        if self._fallback is None:
            self._fallback = self._new_lsq()
        w = 2.0 * RESERVE_WEIGHT
        status, x, it, dt = self._fallback.solve(at, tt, w, self._two, None)
        result = self._finish(status, x, it, dt, a_mat, tau, phase, (at, w, self._two), None)
        self._after_piqp(result)  # the reserve optimum, near the bounds the torque pushes at, seeds the next frame
        if result.status is FrameStatus.SOLVED:
            result.status = FrameStatus.RESERVE
            self._count(FrameStatus.RESERVE)
        return result

    def _new_lsq(self) -> LeastSquaresQP:
        return LeastSquaresQP(
            len(self.groups), len(self.coordinates), self._lb, self._ub, self.backend, self.eps, self.max_iter
        )

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

    def _invalid(self, tau: np.ndarray, phase: float | None, reason: str) -> FrameResult:
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
            solver="none",
            reason=reason,
        )
        self._count(FrameStatus.INVALID_INPUT)
        return result

    def _count(self, status: FrameStatus) -> None:
        self._count_key(status.value)

    def _count_key(self, key: str) -> None:
        first = key not in self.flag_counts
        self.flag_counts[key] = self.flag_counts.get(key, 0) + 1
        if first:
            log.info("frame %d flagged %r (further occurrences are counted in flag_counts)", self.frames, key)

"""Hot-started primal active-set solve of the per-frame box-constrained least-squares QP, compiled, KKT-certified.

Problem (the ``proposed`` / ``hybrid`` / reserve shape of :mod:`msk_core.estimate.qp`), with A = R diag(F_max) and the
per-coordinate capacity scale c_n = max(sum_g |A_ng|, c_min):

    min 1/2 w |A~ a - t~|^2 + 1/2 sum_g d_g (a_g - mu_g)^2,   lb <= a <= ub,   A~ = diag(1/c) A,  t~ = tau / c

Strictly convex (d > 0), so the optimum is unique and the KKT conditions certify it: on the free set the gradient is
zero, at a lower bound it is >= 0, at an upper bound <= 0. Consecutive frames of a movement share almost the same
active set, so the classical primal active-set method (Nocedal & Wright, Numerical Optimization, 2nd ed., alg. 16.3)
started from the previous frame's solution and active set usually ends after one equality-constrained solve (a
solve of the free block's normal equations, done through the Woodbury identity as an m x m system, m = number
of coordinates) with the certificate in hand. When it does not within
``max_iter`` working-set changes (a cycle, a degenerate frame, a failed factorisation) it says so and the caller
solves the frame with PIQP instead: the answer is always either certified here or PIQP's.

``so`` (min a'a s.t. A~ a = t~, lb <= a <= ub) has its own kernel, :func:`solve_min_norm_eq`: the same method on
the same working-set steps, each working set's minimiser from the m x m system (A~_F A~_F') lam = -2 (t~ - A~_B a_B),
a_F = -A~_F' lam / 2, certified by the signs of the bound multipliers 2 a_i + A~_i' lam and by the equality's residual.

Why this exists: PIQP (interior point) takes no starting point, and on a 19-group frame its ~8 iterations cost
~40 µs; this method reuses what the last frame learned and typically costs a few µs.
"""

from __future__ import annotations

from collections.abc import Callable

import numba
import numpy as np

Array = np.ndarray

#: result codes of :func:`solve_box_lsq`
CERTIFIED, NOT_CONVERGED, FACTORISATION_FAILED = 0, 1, 2
#: working-set states
LOWER, FREE, UPPER = -1, 0, 1
#: sign tolerance of the multipliers, relative to the problem's gradient scale (see the kernel)
MULTIPLIER_TOL = 1e-10
#: ``so``: a working set's A~_F A~_F' counts as singular when a squared Cholesky pivot falls below this times its
#: largest diagonal entry (A~'s rows have unit 1-norm)
SINGULAR_TOL = 1e-12
#: ``so``: weight of the scaled residual in the penalty problem whose working set restarts a failed path
PENALTY_WEIGHT = 1e6
#: ``so``: largest scaled torque residual |A~ a - t~| (fraction of the coordinate's capacity) of a certified optimum
EQUALITY_TOL = 1e-9
#: an activation this close to its lower or upper bound counts as at it (the Laplace std's free set)
BOUND_TOL = 1.0e-6
#: ``so``'s Laplace std from the m x m system: the squared Cholesky pivots of A~_F D^-1 A~_F' must stay above this
#: times its largest diagonal entry (cond <~ 1e6, so the cancelling variance is off by <~ 1e-10), else the SVD path
STD_PIVOT_TOL = 1e-6


def _jit(fn: Callable) -> Callable:
    try:
        return numba.njit(cache=True)(fn)
    except RuntimeError:  # no writable cache location: compile in memory at first call
        return numba.njit(fn)


def _part(fn: Callable) -> Callable:
    """A step of :func:`solve_box_lsq`, inlined into it by numba (the kernel stays one call: no per-step call cost)."""
    try:
        return numba.njit(cache=True, inline="always")(fn)
    except RuntimeError:
        return numba.njit(inline="always")(fn)


@_jit
def _solve_free(at, w, d, rhs, free_idx, nf, s_mat, z, y):
    """y[:nf] = H_FF^-1 rhs[:nf] with H = w A~'A~ + diag(d), by the Woodbury identity: only an m x m system
    (m coordinates << G groups): H_FF^-1 = D^-1 - D^-1 A_F' (I/w + A_F D^-1 A_F')^-1 A_F D^-1.
    False when the m x m capacitance matrix is not numerically positive definite (it is, for d > 0 and w > 0)."""
    m = at.shape[0]
    for a in range(nf):  # u = D^-1 rhs
        y[a] = rhs[a] / d[free_idx[a]]
    _free_gram(at, d, free_idx, nf, s_mat)
    for i in range(m):  # S = I/w + A_F D^-1 A_F' (lower triangle), z = A_F u
        s_mat[i, i] += 1.0 / w
        acc = 0.0
        for a in range(nf):
            acc += at[i, free_idx[a]] * y[a]
        z[i] = acc
    if not _cholesky_solve(s_mat, z, m, 0.0):
        return False
    for a in range(nf):  # y = u - D^-1 A_F' z
        fi = free_idx[a]
        acc = 0.0
        for i in range(m):
            acc += at[i, fi] * z[i]
        y[a] -= acc / d[fi]
    return True


@_jit
def solve_box_lsq(
    r, f_max, tau, w, mean_table, prec_table, row0, row1, frac, lb, ub, min_scale, x, state, max_iter, with_std
):
    """Solve the frame's QP from the working set in ``state`` and the point ``x`` (both updated in place).

    r: moment arms (m, G); tau: (m,); f_max, lb, ub, x: (G,); state: int8 (G,) LOWER/FREE/UPPER. The prior
    (mu, d) is interpolated here, mu = (1 - frac) mean_table[row0] + frac mean_table[row1] (d from prec_table alike),
    to spare the per-frame array operations in Python.
    Returns (code, working-set changes, out (m + 4, G): rows A~ | x | forces | d | Laplace std (when certified and
    ``with_std``: :func:`_laplace_std`; the calibration's solves do not read it), torques (2, m): model | residual).
    ``x`` holds the certified optimum when code == CERTIFIED; otherwise its content is unspecified (re-seed it).
    """
    m, g = r.shape
    out = np.empty((m + 4, g))
    at = out[:m]
    d = out[m + 2]
    mu = np.empty(g)
    _interpolate_prior(mean_table, prec_table, row0, row1, frac, mu, d)
    tt = np.empty(m)
    _scale_rows(r, f_max, tau, min_scale, at, tt)
    _feasible_start(state, lb, ub, x)
    code, changes = _iterate(at, tt, w, d, mu, lb, ub, x, state, max_iter, False)
    if with_std and code == CERTIFIED:
        _laplace_std(at, w, d, False, x, lb, ub, out[m + 3])
    return code, changes, out, _forces_and_torques(r, f_max, tau, x, out)


@_jit
def solve_min_norm_eq(r, f_max, tau, lb, ub, min_scale, x, state, max_iter):
    """Solve ``so``'s QP, min a'a s.t. A~ a = t~, lb <= a <= ub, from the working set in ``state`` and the point
    ``x`` (both updated in place), as :func:`solve_box_lsq` does the least-squares one.

    Returns (code, working-set changes, out (m + 4, G): rows A~ | x | forces | 2 (the Hessian's diagonal) | Laplace
    std (when certified), torques (2, m): model | residual). code is FACTORISATION_FAILED when a working set leaves A~_F A~_F' singular (fewer free
    groups than coordinates, a coordinate all of whose groups are held: its torque is then met only by the held
    values, if at all) even after one restart from the working set of the penalty problem (below), NOT_CONVERGED
    after ``max_iter`` changes; the caller then asks PIQP, which also tells an infeasible frame (the reserve
    fallback) apart.
    """
    m, g = r.shape
    out = np.empty((m + 4, g))
    at = out[:m]
    out[m + 2] = 2.0
    tt = np.empty(m)
    _scale_rows(r, f_max, tau, min_scale, at, tt)
    _feasible_start(state, lb, ub, x)
    code, changes = _iterate(at, tt, 0.0, out[m + 2], out[m + 2], lb, ub, x, state, max_iter, True)
    if code == FACTORISATION_FAILED and changes < max_iter:
        # the path from a start off the equality ran into a singular working set: take the working set of the
        # penalty problem min a'a + PENALTY_WEIGHT |A~ a - t~|^2 (strictly convex: always found), start again there
        d = out[m + 2]
        code, more = _iterate(at, tt, 2.0 * PENALTY_WEIGHT, d, np.zeros(g), lb, ub, x, state, max_iter - changes, False)
        changes += more
        if code == CERTIFIED:
            code, more = _iterate(at, tt, 0.0, d, d, lb, ub, x, state, max_iter - changes, True)
            changes += more
        elif code == NOT_CONVERGED:
            code = FACTORISATION_FAILED
    if code == CERTIFIED:
        _laplace_std(at, 0.0, out[m + 2], True, x, lb, ub, out[m + 3])
    return code, changes, out, _forces_and_torques(r, f_max, tau, x, out)


@_part
def _iterate(
    at: Array,
    tt: Array,
    w: float,
    d: Array,
    mu: Array,
    lb: Array,
    ub: Array,
    x: Array,
    state: Array,
    max_iter: int,
    equality: bool,
) -> tuple[int, int]:
    """The active-set iterations from the working set in ``state`` and ``x`` (in the box): (code, changes). One loop
    for both problems; they differ in each working set's minimiser and in the bound multipliers:

    * least squares (``equality`` False, :func:`solve_box_lsq`): the minimiser over the free set F, the held groups B
      fixed at their bounds, solves H_FF y = w A~_F'(t~ - A~_B x_B) + d_F mu_F; a bound's multiplier is its gradient
      w A~_i'(A~ x - t~) + d_i (x_i - mu_i).
    * ``so`` (``equality`` True, :func:`solve_min_norm_eq`; ``w``, ``d``, ``mu`` unused): a_F = -A_F' lam / 2 with
      (A_F A_F') lam = -2 (t - A_B a_B), i.e. a_F = A_F' v, (A_F A_F') v = t - A_B a_B, lam = -2 v; a bound's
      multiplier is g_i = 2 a_i + A_i' lam. The start need not meet the equality (the last frame's optimum): a
      blocked step shrinks its residual by (1 - alpha), the first full step removes it, and from there every step
      stays on the equality (the textbook method); a full step certifies only when it meets the equality to
      ``EQUALITY_TOL``.

    Certified when the full step's multipliers all have their sign (>= 0 at a lower bound, <= 0 at an upper one)."""
    m, g = at.shape
    tol = 0.0 if equality else _multiplier_tolerance(at, tt, w, d, mu)
    free_idx = np.empty(g, dtype=np.int64)
    rhs = np.empty(g)
    y = np.empty(g)
    v = np.empty(m)
    e = np.empty(m)
    s_mat = np.empty((m, m))
    z = np.empty(m)
    grad = np.empty(g)
    code = NOT_CONVERGED
    changes = 0
    while True:
        nf = _collect_free(state, free_idx)
        for n in range(m):  # v = t~ - A~_B x_B
            s = tt[n]
            for j in range(g):
                if state[j] != FREE:
                    s -= at[n, j] * x[j]
            v[n] = s
        if equality:
            solved = _min_norm_free(at, v, free_idx, nf, s_mat, y)
        else:
            _least_squares_rhs(at, w, d, mu, v, free_idx, nf, rhs)
            solved = nf == 0 or _solve_free(at, w, d, rhs, free_idx, nf, s_mat, z, y)
        if not solved:
            code = FACTORISATION_FAILED
            break
        # step towards it, stopped by the first bound in the way
        block = _step(free_idx, nf, y, lb, ub, x)
        if block >= 0:
            if changes >= max_iter:
                break
            changes += 1
            _hold(block, lb, ub, x, state)
            continue
        # full step: x is the working set's minimiser; the multipliers of its bounds decide
        worst_residual = _residual(at, tt, x, e)
        if equality:
            if worst_residual > EQUALITY_TOL:
                break  # numerically no solution of the equality in this working set: not certified
            tol = MULTIPLIER_TOL * _so_gradient(at, x, v, grad)
        else:
            _least_squares_gradient(at, w, d, mu, x, state, e, grad)
        worst_i = _most_violated(state, grad, tol)
        if worst_i < 0:
            code = CERTIFIED
            break
        if changes >= max_iter:
            break
        changes += 1
        state[worst_i] = FREE  # the most violated bound is released
    return code, changes


@_part
def _least_squares_rhs(
    at: Array, w: float, d: Array, mu: Array, v: Array, free_idx: Array, nf: int, rhs: Array
) -> None:
    """rhs_F = w A~_F' v + d_F mu_F with v = t~ - A~_B x_B: the right-hand side of the free block's normal equations."""
    m = at.shape[0]
    for a in range(nf):
        fi = free_idx[a]
        s = 0.0
        for n in range(m):
            s += at[n, fi] * v[n]
        rhs[a] = w * s + d[fi] * mu[fi]


@_part
def _residual(at: Array, tt: Array, x: Array, e: Array) -> float:
    """e = A~ x - t~; returns max |e|."""
    m, g = at.shape
    worst = 0.0
    for n in range(m):
        s = -tt[n]
        for j in range(g):
            s += at[n, j] * x[j]
        e[n] = s
        worst = max(worst, abs(s))
    return worst


@_part
def _least_squares_gradient(
    at: Array, w: float, d: Array, mu: Array, x: Array, state: Array, e: Array, grad: Array
) -> None:
    """The held groups' gradients w A~_i' e + d_i (x_i - mu_i), e = A~ x - t~: their bound multipliers."""
    m, g = at.shape
    for i in range(g):
        if state[i] != FREE:
            s = 0.0
            for n in range(m):
                s += at[n, i] * e[n]
            grad[i] = w * s + d[i] * (x[i] - mu[i])


@_part
def _min_norm_free(at: Array, v: Array, free_idx: Array, nf: int, s_mat: Array, y: Array) -> bool:
    """``so``'s minimiser over the free set: v <- (A~_F A~_F')^-1 v, y = A~_F' v; False when A~_F A~_F' is singular
    (its squared Cholesky pivots below ``SINGULAR_TOL`` times its largest diagonal entry)."""
    m = at.shape[0]
    big = 0.0
    for i in range(m):  # S = A_F A_F' (lower triangle)
        for k in range(i + 1):
            acc = 0.0
            for a in range(nf):
                acc += at[i, free_idx[a]] * at[k, free_idx[a]]
            s_mat[i, k] = acc
        big = max(big, s_mat[i, i])
    if not _cholesky_solve(s_mat, v, m, SINGULAR_TOL * big):
        return False
    for a in range(nf):  # y = A_F' v
        acc = 0.0
        for i in range(m):
            acc += at[i, free_idx[a]] * v[i]
        y[a] = acc
    return True


@_part
def _so_gradient(at: Array, x: Array, v: Array, grad: Array) -> float:
    """grad = 2 a + A~' lam = 2 (a - A~' v) (so's gradient of the Lagrangian: the bound multipliers where held);
    returns its scale, max(2, max_j 2 sum_i |A~_ij v_i|)."""
    m, g = at.shape
    scale = 2.0
    for j in range(g):
        acc = 0.0
        size = 0.0
        for i in range(m):
            acc += at[i, j] * v[i]
            size += abs(at[i, j] * v[i])
        grad[j] = 2.0 * (x[j] - acc)
        scale = max(scale, 2.0 * size)
    return scale


@_part
def _collect_free(state: Array, free_idx: Array) -> int:
    """free_idx[:nf] = the free variables of the working set; returns nf."""
    nf = 0
    for i in range(state.shape[0]):
        if state[i] == FREE:
            free_idx[nf] = i
            nf += 1
    return nf


@_part
def _hold(block: int, lb: Array, ub: Array, x: Array, state: Array) -> None:
    """The blocking variable of a step joins the working set at the bound it hit."""
    if x[block] - lb[block] <= ub[block] - x[block]:
        state[block], x[block] = LOWER, lb[block]
    else:
        state[block], x[block] = UPPER, ub[block]


@_part
def _most_violated(state: Array, grad: Array, tol: float) -> int:
    """The held variable whose bound multiplier (the objective's gradient ``grad``, read where held) has the wrong
    sign by more than ``tol`` - most of all; -1: none (a lower bound needs grad >= 0, an upper one grad <= 0)."""
    worst = tol
    worst_i = -1
    for i in range(state.shape[0]):
        if state[i] == FREE:
            continue
        violation = -grad[i] if state[i] == LOWER else grad[i]
        if violation > worst:
            worst, worst_i = violation, i
    return worst_i


@_part
def _free_gram(at: Array, d: Array, free_idx: Array, nf: int, s_mat: Array) -> None:
    """The lower triangle of A~_F D^-1 A~_F' (F: the first ``nf`` groups of ``free_idx``) into ``s_mat``: the m x m
    system of the Woodbury solve and of the Laplace std."""
    m = at.shape[0]
    for i in range(m):
        for k in range(i + 1):
            acc = 0.0
            for a in range(nf):
                j = free_idx[a]
                acc += at[i, j] * at[k, j] / d[j]
            s_mat[i, k] = acc


@_part
def _cholesky_solve(s_mat: Array, z: Array, m: int, floor: float) -> bool:
    """z <- S^-1 z for the symmetric S in the lower triangle of s_mat[:m, :m], factorised in place (S = L L');
    False when a squared pivot is not above ``floor`` (S not numerically positive definite)."""
    for i in range(m):
        for j in range(i + 1):
            acc = s_mat[i, j]
            for k in range(j):
                acc -= s_mat[i, k] * s_mat[j, k]
            if i == j:
                if not acc > floor:
                    return False
                s_mat[i, i] = np.sqrt(acc)
            else:
                s_mat[i, j] = acc / s_mat[j, j]
    for i in range(m):  # forward: L u = z
        acc = z[i]
        for k in range(i):
            acc -= s_mat[i, k] * z[k]
        z[i] = acc / s_mat[i, i]
    for i in range(m - 1, -1, -1):  # back: L' v = u
        acc = z[i]
        for k in range(i + 1, m):
            acc -= s_mat[k, i] * z[k]
        z[i] = acc / s_mat[i, i]
    return True


@_part
def _interpolate_prior(
    mean_table: Array, prec_table: Array, row0: int, row1: int, frac: float, mu: Array, d: Array
) -> None:
    """mu, d: the prior's mean and precision between table rows row0 and row1 (fraction frac of the way)."""
    for j in range(mu.shape[0]):
        mu[j] = mean_table[row0, j] + frac * (mean_table[row1, j] - mean_table[row0, j])
        d[j] = prec_table[row0, j] + frac * (prec_table[row1, j] - prec_table[row0, j])


@_part
def _scale_rows(r: Array, f_max: Array, tau: Array, min_scale: float, at: Array, tt: Array) -> None:
    """at = A~ = diag(1/c) R diag(F_max), tt = t~ = tau / c, with c_n = max(sum_g |A_ng|, min_scale)."""
    m, g = r.shape
    for n in range(m):
        s = 0.0
        for j in range(g):
            at[n, j] = r[n, j] * f_max[j]
            s += abs(at[n, j])
        if s < min_scale:
            s = min_scale
        for j in range(g):
            at[n, j] /= s
        tt[n] = tau[n] / s


@_part
def _multiplier_tolerance(at: Array, tt: Array, w: float, d: Array, mu: Array) -> float:
    """The multipliers' sign tolerance: MULTIPLIER_TOL times the scale of the gradient
    w A~'(A~ a - t~) + d (a - mu) of 1/2 w |A~ a - t~|^2 + 1/2 sum d (a - mu)^2."""
    m, g = at.shape
    grad_scale = 0.0
    for j in range(g):
        s = 0.0
        for n in range(m):
            s += abs(at[n, j]) * (abs(tt[n]) + abs(at[n, j]))
        grad_scale = max(grad_scale, w * s + d[j] * (1.0 + abs(mu[j])))
    return MULTIPLIER_TOL * grad_scale


@_part
def _feasible_start(state: Array, lb: Array, ub: Array, x: Array) -> None:
    """x moved to a feasible point consistent with the working set: held variables at their bound, free ones
    clipped into the box."""
    for i in range(x.shape[0]):
        if state[i] == LOWER:
            x[i] = lb[i]
        elif state[i] == UPPER:
            x[i] = ub[i]
        else:
            x[i] = min(max(x[i], lb[i]), ub[i])


@_part
def _step(free_idx: Array, nf: int, y: Array, lb: Array, ub: Array, x: Array) -> int:
    """Step the free variables of x towards y, stopped by the first bound in the way; returns the blocking
    variable (-1: the full step was taken)."""
    alpha = 1.0
    block = -1
    for a in range(nf):
        fi = free_idx[a]
        p = y[a] - x[fi]
        if p < 0.0 and x[fi] + p < lb[fi]:
            t = (lb[fi] - x[fi]) / p
            if t < alpha:
                alpha, block = t, fi
        elif p > 0.0 and x[fi] + p > ub[fi]:
            t = (ub[fi] - x[fi]) / p
            if t < alpha:
                alpha, block = t, fi
    for a in range(nf):
        fi = free_idx[a]
        x[fi] += alpha * (y[a] - x[fi])
    return block


@_part
def _laplace_std(at: Array, w: float, d: Array, equality: bool, x: Array, lb: Array, ub: Array, std: Array) -> None:
    """std: the Laplace std of each activation at the optimum ``x``, what :func:`msk_core.estimate.laplace.laplace_std`
    gives from the frame's Hessian H = w A~'A~ + diag(d) (``equality``: with the rows A~ as equality constraints).

    0 at a bound (within ``BOUND_TOL``); on the free set F the diagonal of H_FF^-1 by the Woodbury identity,
    1/d_j - a_j' S^-1 a_j / d_j^2 with S = I/w + A~_F D^-1 A~_F' (a_j: column j of A~), an m x m system; with the
    equality the covariance on its null space, H^-1 - H^-1 A' (A H^-1 A')^-1 A H^-1, whose diagonal is the same
    expression with S = A~_F D^-1 A~_F'. With the equality, no more free groups than rows leave no null space (all
    0), and the expression cancels (its error grows as eps cond(S)), so S must be conditioned within
    ``STD_PIVOT_TOL``. NaN everywhere when S fails that or is not numerically positive definite (redundant rows):
    the caller then computes it the general way."""
    m, g = at.shape
    s_mat = np.zeros((m, m))
    u = np.zeros(m)
    big = 0.0
    free = np.empty(g, dtype=np.int64)
    n_free = 0
    for j in range(g):
        std[j] = 0.0
        if lb[j] + BOUND_TOL < x[j] < ub[j] - BOUND_TOL:
            free[n_free] = j
            n_free += 1
    _free_gram(at, d, free, n_free, s_mat)
    for i in range(m):
        big = max(big, s_mat[i, i])
        if not equality:
            s_mat[i, i] += 1.0 / w if w > 0.0 else np.inf
    if not _cholesky_solve(s_mat, u, m, STD_PIVOT_TOL * big if equality else 0.0):
        for j in range(g):
            std[j] = np.nan
        return
    if equality and n_free <= m:
        return  # the equality fixes every free group: no spread
    for a in range(n_free):
        j = free[a]
        quad = 0.0
        for i in range(m):  # L u = a_j, a_j' S^-1 a_j = |u|^2
            acc = at[i, j]
            for k in range(i):
                acc -= s_mat[i, k] * u[k]
            u[i] = acc / s_mat[i, i]
            quad += u[i] * u[i]
        std[j] = np.sqrt(max(1.0 / d[j] - quad / (d[j] * d[j]), 0.0))


@_part
def _forces_and_torques(r: Array, f_max: Array, tau: Array, x: Array, out: Array) -> Array:
    """Rows x and forces of ``out``; returns torques (2, m): the model's (R F) and the residual (R F - tau)."""
    m, g = r.shape
    torques = np.empty((2, m))
    for j in range(g):
        out[m, j] = x[j]
        out[m + 1, j] = f_max[j] * x[j]
    for n in range(m):
        s = 0.0
        for j in range(g):
            s += r[n, j] * out[m + 1, j]
        torques[0, n] = s
        torques[1, n] = s - tau[n]
    return torques


@_jit
def seed_state(x, lb, ub, tol, state):
    """Working set of a solution found elsewhere (PIQP): variables within ``tol`` of a bound are held there."""
    for i in range(x.shape[0]):
        if x[i] <= lb[i] + tol:
            state[i] = LOWER
        elif x[i] >= ub[i] - tol:
            state[i] = UPPER
        else:
            state[i] = FREE


def new_state(n_groups: int) -> tuple[np.ndarray, np.ndarray]:
    """(x, working set) to start from: everything free at 0 (the first frame may take a few changes)."""
    return np.zeros(n_groups), np.zeros(n_groups, dtype=np.int8)

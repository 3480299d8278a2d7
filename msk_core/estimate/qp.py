"""The two QP shapes of per-frame estimation on warm PIQP solvers, with a dense and a sparse backend.

``LeastSquaresQP``:  min 1/2 w |A~ a - t~|^2 + 1/2 a' diag(d) a + c_a' a,  lb <= a <= ub
``EqualityQP``:      min a'a  s.t.  A~ a = t~,  lb <= a <= ub

Dense backend (``piqp.DenseSolver``): the least-squares form is condensed to P = w A~'A~ + diag(d), a G x G dense
matrix. Sparse backend (``piqp.SparseSolver``): residual variables e = A~ a - t~ are lifted into the problem,
x = [a; e], P = diag(d, w) and the equality [A~, -I] x = t~, so the KKT system is diagonal plus n_coordinates dense
rows - far cheaper than a dense G x G factorisation for many groups (150 groups: ~5x). Both give the same optimum.
Each solver is set up once, then only ``update()``-d with new values in a fixed sparsity pattern (explicit zeros kept).
"""

from __future__ import annotations

import time
from enum import Enum

import numpy as np
import piqp
import scipy.sparse as sp

SPARSE_FROM_GROUPS = 40  # "auto" picks the sparse backend from this many groups up (measured crossover ~20-40)


class Backend(str, Enum):
    AUTO = "auto"
    DENSE = "dense"
    SPARSE = "sparse"


def resolve_backend(backend: Backend | str, n_groups: int) -> Backend:
    b = Backend(backend)
    if b is Backend.AUTO:
        return Backend.SPARSE if n_groups >= SPARSE_FROM_GROUPS else Backend.DENSE
    return b


def _configure(solver, eps: float, max_iter: int):
    s = solver.settings
    s.eps_abs = eps
    s.eps_rel = eps
    s.max_iter = max_iter
    s.verbose = False
    s.compute_timings = False
    s.preconditioner_reuse_on_update = True  # consecutive frames have nearly the same scaling
    return solver


def _full_csc(m: int, n: int) -> sp.csc_matrix:
    """m x n CSC matrix with every entry stored (values set later through .data in column-major order)."""
    indices = np.tile(np.arange(m, dtype=np.int32), n)
    indptr = np.arange(0, m * (n + 1), m, dtype=np.int32)
    return sp.csc_matrix((np.zeros(m * n), indices, indptr), shape=(m, n))


class LeastSquaresQP:
    def __init__(self, n_groups: int, n_coordinates: int, lb, ub, backend: Backend, eps: float, max_iter: int):
        self.g, self.m = n_groups, n_coordinates
        self.backend = backend
        self.eps, self.max_iter = eps, max_iter
        self.solver: piqp.SparseSolver | piqp.DenseSolver | None = None  # set up on the first solve
        if backend is Backend.SPARSE:
            g, m = n_groups, n_coordinates
            n = g + m
            self.x_l = np.r_[lb, np.full(m, -np.inf)]
            self.x_u = np.r_[ub, np.full(m, np.inf)]
            self.p = sp.csc_matrix(
                (np.ones(n), np.arange(n, dtype=np.int32), np.arange(n + 1, dtype=np.int32)), shape=(n, n)
            )
            indices = np.r_[np.tile(np.arange(m, dtype=np.int32), g), np.arange(m, dtype=np.int32)]
            indptr = np.r_[np.arange(0, m * (g + 1), m), m * g + np.arange(1, m + 1)].astype(np.int32)
            self.a = sp.csc_matrix((np.r_[np.zeros(m * g), -np.ones(m)], indices, indptr), shape=(m, n))
            self.c = np.zeros(n)
        else:
            self.x_l, self.x_u = lb, ub

    def solve(
        self, at: np.ndarray, tt: np.ndarray, w: float, d: np.ndarray, c_a: np.ndarray | None
    ) -> tuple[piqp.Status, np.ndarray, int, float]:
        """(PIQP status, activations, iterations, seconds) of the least-squares QP."""
        if self.backend is Backend.SPARSE:
            g = self.g
            self.p.data[:g] = d
            self.p.data[g:] = w
            self.a.data[: g * self.m] = at.T.ravel()
            if c_a is not None:
                self.c[:g] = c_a
            if self.solver is None:
                self.solver = _configure(piqp.SparseSolver(), self.eps, self.max_iter)
                self.solver.setup(self.p, self.c, self.a, tt, x_l=self.x_l, x_u=self.x_u)
            else:
                self.solver.update(P=self.p, c=self.c, A=self.a, b=tt)
        else:
            hess = at.T @ at
            hess *= w
            hess.flat[:: self.g + 1] += d
            c = at.T @ tt
            c *= -w
            if c_a is not None:
                c += c_a
            if self.solver is None:
                self.solver = _configure(piqp.DenseSolver(), self.eps, self.max_iter)
                self.solver.setup(hess.T, c, x_l=self.x_l, x_u=self.x_u)  # hess.T: F-ordered view (symmetric)
            else:
                self.solver.update(P=hess.T, c=c)
        t0 = time.perf_counter()
        status = self.solver.solve()
        dt = time.perf_counter() - t0
        res = self.solver.result
        return status, res.x[: self.g].copy(), int(res.info.iter), dt


class EqualityQP:
    def __init__(self, n_groups: int, n_coordinates: int, lb, ub, backend: Backend, eps: float, max_iter: int):
        self.g, self.m = n_groups, n_coordinates
        self.backend = backend
        self.eps, self.max_iter = eps, max_iter
        self.lb, self.ub = lb, ub
        self.solver: piqp.SparseSolver | piqp.DenseSolver | None = None  # set up on the first solve
        self.c = np.zeros(n_groups)
        self.p: sp.csc_matrix | np.ndarray
        if backend is Backend.SPARSE:
            self.p = sp.identity(n_groups, format="csc") * 2.0
            self.a = _full_csc(n_coordinates, n_groups)
        else:
            self.p = np.asfortranarray(2.0 * np.eye(n_groups))

    def solve(self, at: np.ndarray, tt: np.ndarray) -> tuple[piqp.Status, np.ndarray, int, float]:
        """(PIQP status, activations, iterations, seconds) of the equality-constrained QP."""
        a: sp.csc_matrix | np.ndarray
        if self.backend is Backend.SPARSE:
            self.a.data[:] = at.T.ravel()
            a = self.a
        else:
            a = np.asfortranarray(at)
        if self.solver is None:
            self.solver = _configure(
                piqp.SparseSolver() if self.backend is Backend.SPARSE else piqp.DenseSolver(), self.eps, self.max_iter
            )
            self.solver.setup(self.p, self.c, a, tt, x_l=self.lb, x_u=self.ub)
        else:
            self.solver.update(A=a, b=tt)  # P = 2I and c = 0 never change
        t0 = time.perf_counter()
        status = self.solver.solve()
        dt = time.perf_counter() - t0
        res = self.solver.result
        return status, res.x[: self.g].copy(), int(res.info.iter), dt

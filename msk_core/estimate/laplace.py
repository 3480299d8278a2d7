"""Laplace approximation of each activation's uncertainty from the curvature of the problem at the optimum.

The objective J(a) is read as a negative log-density (up to a constant), so its Hessian H is the precision of a
Gaussian around the optimum. Activations at a bound are pinned by the bound and get std 0; on the free set F the
covariance is inv(H_FF); with equality constraints E_F a_F = const (static optimisation) it is the inverse of the
Hessian reduced to the null space Z of E_F: Z (Z' H_FF Z)^-1 Z'.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import lapack

# LAPACK directly (dgesdd, dpotrf, dtrtri): numpy.linalg's wrappers cost 8-20 us a call on these 10-20-variable
# matrices, about ten times the factorisations themselves, and the live estimator asks every frame of every method.


def laplace_std(hessian: np.ndarray, free: np.ndarray, equality: np.ndarray | None = None) -> np.ndarray:
    """Standard deviation per variable; 0 for variables at a bound or fixed by the equality constraints.

    Only the diagonal of the covariance is formed (sums of squares of the inverse Cholesky factor's columns), not
    the covariance itself: the live estimator asks for it every frame."""
    n = hessian.shape[0]
    std = np.zeros(n)
    idx = np.flatnonzero(free)
    if idx.size == 0:
        return std
    h = hessian.take(idx, axis=0).take(idx, axis=1)
    if equality is None or equality.size == 0:
        variance = _inverse_diagonal(h, None)
    else:
        e = equality.take(idx, axis=1)
        # Null space of the active equality rows via SVD (rank-revealing, robust to redundant rows).
        _, s, vt, info = lapack.dgesdd(e, full_matrices=1)
        if info != 0:  # did not converge: numpy's wrapper says why
            _, s, vt = np.linalg.svd(e, full_matrices=True)
        rank = int(np.sum(s > s.max(initial=0.0) * 1e-10)) if s.size else 0
        z = vt[rank:].T
        if z.shape[1] == 0:
            return std
        variance = _inverse_diagonal(z.T @ h @ z, z)
    std[idx] = np.sqrt(np.maximum(variance, 0.0))
    return std


def _inverse_diagonal(h: np.ndarray, z: np.ndarray | None) -> np.ndarray:
    """The diagonal of ``z inv(h) z'`` (``z`` None: of ``inv(h)``) for a symmetric positive (semi)definite ``h``;
    with the pseudo-inverse when ``h`` is singular (flat directions)."""
    c, info = lapack.dpotrf(h, lower=1)  # h = c c' (the other triangle zeroed)
    if info == 0:
        w, info = lapack.dtrtri(c, lower=1)  # inv(h) = w' w
    if info != 0:  # not positive definite: flat directions
        p = np.linalg.pinv(h, hermitian=True)
        return np.diagonal(p).copy() if z is None else np.einsum("ij,jk,ik->i", z, p, z)
    if z is not None:
        w = w @ z.T  # z inv(h) z' = (w z')' (w z')
    return np.einsum("ij,ij->j", w, w)

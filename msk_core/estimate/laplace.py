"""Laplace approximation of each activation's uncertainty from the curvature of the problem at the optimum.

The objective J(a) is read as a negative log-density (up to a constant), so its Hessian H is the precision of a
Gaussian around the optimum. Activations at a bound are pinned by the bound and get std 0; on the free set F the
covariance is inv(H_FF); with equality constraints E_F a_F = const (static optimisation) it is the inverse of the
Hessian reduced to the null space Z of E_F: Z (Z' H_FF Z)^-1 Z'.
"""

from __future__ import annotations

import numpy as np


def laplace_std(hessian: np.ndarray, free: np.ndarray, equality: np.ndarray | None = None) -> np.ndarray:
    """Standard deviation per variable; 0 for variables at a bound or fixed by the equality constraints."""
    n = hessian.shape[0]
    std = np.zeros(n)
    idx = np.flatnonzero(free)
    if idx.size == 0:
        return std
    h = hessian[np.ix_(idx, idx)]
    if equality is None or equality.size == 0:
        cov = _inv_psd(h)
    else:
        e = equality[:, idx]
        # Null space of the active equality rows via SVD (rank-revealing, robust to redundant rows).
        _, s, vt = np.linalg.svd(e, full_matrices=True)
        rank = int(np.sum(s > s.max(initial=0.0) * 1e-10)) if s.size else 0
        z = vt[rank:].T
        if z.shape[1] == 0:
            return std
        cov = z @ _inv_psd(z.T @ h @ z) @ z.T
    std[idx] = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return std


def _inv_psd(h: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive (semi)definite matrix; pseudo-inverse when singular (flat directions)."""
    try:
        c = np.linalg.cholesky(h)
        ci = np.linalg.inv(c)
        return ci.T @ ci
    except np.linalg.LinAlgError:
        return np.linalg.pinv(h, hermitian=True)

"""laplace_std forms only the covariance's diagonal: it equals that of the full covariance, formed explicitly."""

from __future__ import annotations

import numpy as np

from msk_core.estimate.laplace import laplace_std


def _inverse(h: np.ndarray) -> np.ndarray:
    """inv(h) through its Cholesky factor; the pseudo-inverse where the factorisation fails."""
    try:
        ci = np.linalg.inv(np.linalg.cholesky(h))
    except np.linalg.LinAlgError:
        return np.linalg.pinv(h, hermitian=True)
    return ci.T @ ci


def _reference(h: np.ndarray, free: np.ndarray, e: np.ndarray | None) -> np.ndarray:
    """The full covariance Z inv(Z' H Z) Z' on the free set (Z = identity without constraints), its diagonal's root."""
    idx = np.flatnonzero(free)
    h_ff = h[np.ix_(idx, idx)]
    z = np.eye(idx.size)
    if e is not None:
        _, s, vt = np.linalg.svd(e[:, idx], full_matrices=True)
        z = vt[int(np.sum(s > s.max(initial=0.0) * 1e-10)) :].T
    std = np.zeros(h.shape[0])
    if z.shape[1]:
        std[idx] = np.sqrt(np.clip(np.diag(z @ _inverse(z.T @ h_ff @ z) @ z.T), 0.0, None))
    return std


def test_laplace_std_is_the_full_covariances_diagonal():
    rng = np.random.default_rng(3)
    for trial in range(60):
        n = int(rng.integers(3, 20))
        m = rng.normal(size=(n, n - 2))
        h = m @ m.T + (np.eye(n) if trial % 4 else 0.0)  # every fourth of rank n - 2 (flat directions): pseudo-inverse
        free = rng.random(n) > 0.2
        e = rng.normal(size=(int(rng.integers(1, 5)), n)) if trial % 2 else None
        if e is not None and e.shape[0] > 1 and trial % 3 == 0:
            e[1] = 2.0 * e[0]  # a redundant row
        expected = _reference(h, free, e)
        got = laplace_std(h, free, e)
        np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-9 * max(1.0, float(expected.max())))
        assert np.all(got[~free] == 0.0)

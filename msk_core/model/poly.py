"""Polynomial surrogates of muscle-tendon length in normalised coordinates, with analytic derivatives.

A pack stores one shared monomial basis (exponent rows over all pack coordinates, each closed under differentiation)
and coefficient matrices; x = (q - centre) / half_width maps each fitted range onto [-1, 1].
"""

from __future__ import annotations

import itertools

import numpy as np


def total_degree_exponents(n_vars: int, degree: int) -> np.ndarray:
    """All exponent tuples of n_vars variables with total degree <= degree, shape (M, n_vars)."""
    rows = [e for e in itertools.product(range(degree + 1), repeat=n_vars) if sum(e) <= degree]
    rows.sort(key=lambda e: (sum(e), e))
    return np.array(rows, dtype=np.int64).reshape(len(rows), n_vars)


def monomials(x: np.ndarray, exponents: np.ndarray) -> np.ndarray:
    """Monomials of samples x (S, n) for exponents (M, n) -> (S, M)."""
    x = np.atleast_2d(x)
    powers = x[:, :, None] ** np.arange(exponents.max(initial=0) + 1)[None, None, :]  # (S, n, D+1)
    cols = np.arange(exponents.shape[1])
    return np.prod(powers[:, cols[None, :], exponents], axis=2)


def monomial_derivatives(x: np.ndarray, exponents: np.ndarray, var: int) -> np.ndarray:
    """d(monomial)/dx_var at samples x (S, n) -> (S, M)."""
    lowered = exponents.copy()
    factor = lowered[:, var].astype(float)
    lowered[:, var] = np.maximum(lowered[:, var] - 1, 0)
    return monomials(x, lowered) * factor[None, :]


def derivative_matrix(exponents: np.ndarray, var: int) -> np.ndarray:
    """Linear map D (M, M) with coefficients of d/dx_var: c' = c @ D, in the same (differentiation-closed) basis."""
    index = {tuple(e): i for i, e in enumerate(exponents.tolist())}
    matrix = np.zeros((len(exponents), len(exponents)))
    for i, e in enumerate(exponents.tolist()):
        if e[var] == 0:
            continue
        lowered = list(e)
        lowered[var] -= 1
        matrix[i, index[tuple(lowered)]] = e[var]
    return matrix


def hinge_values(x: np.ndarray, hinges: list[tuple[int, float]]) -> np.ndarray:
    """Truncated powers h, h², h³ (h = max(x_var - knot, 0)) per hinge -> (S, 3H).

    A hinge lets the length's slope (the moment arm) jump at a knot: OpenSim paths that switch wrap objects do.
    """
    cols = []
    for var, knot in hinges:
        h = np.maximum(x[:, var] - knot, 0.0)
        cols += [h, h * h, h * h * h]
    return np.stack(cols, axis=1) if cols else np.zeros((len(x), 0))


def hinge_derivatives(x: np.ndarray, hinges: list[tuple[int, float]], var: int) -> np.ndarray:
    """d/dx_var of :func:`hinge_values`: step, 2h, 3h² for hinges on var, zero otherwise."""
    cols = []
    for hvar, knot in hinges:
        if hvar != var:
            cols += [np.zeros(len(x))] * 3
            continue
        h = np.maximum(x[:, hvar] - knot, 0.0)
        cols += [(x[:, hvar] > knot).astype(float), 2 * h, 3 * h * h]
    return np.stack(cols, axis=1) if cols else np.zeros((len(x), 0))


def fit_length(
    x: np.ndarray, length: np.ndarray, dl_dx: np.ndarray, degree: int, derivative_weight: float = 1.0,
    hinges: list[tuple[int, float]] = (),
) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares fit of l(x) to lengths and their derivatives jointly (Hermite-style).

    x (S, k) normalised coordinates of the k spanned coordinates, length (S,), dl_dx (S, k); hinges index x's
    columns. Returns (exponents (M, k), coefficients (M + 3H,)): monomial coefficients then hinge coefficients.
    """
    k = x.shape[1]
    exponents = total_degree_exponents(k, degree)
    blocks = [np.hstack([monomials(x, exponents), hinge_values(x, list(hinges))])]
    targets = [length]
    for var in range(k):
        blocks.append(derivative_weight * np.hstack([monomial_derivatives(x, exponents, var),
                                                     hinge_derivatives(x, list(hinges), var)]))
        targets.append(derivative_weight * dl_dx[:, var])
    a = np.vstack(blocks)
    b = np.concatenate(targets)
    keep = np.isfinite(b)  # derivatives are NaN where the OpenSim path jumped
    a, b = a[keep], b[keep]
    coef, *_ = np.linalg.lstsq(a, b, rcond=None)
    return exponents, coef

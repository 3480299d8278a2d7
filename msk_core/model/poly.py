"""Polynomial surrogates of muscle-tendon length in normalised coordinates, with analytic derivatives.

A pack stores one shared monomial basis (exponent rows over all pack coordinates, each closed under differentiation)
and coefficient matrices; x = (q - centre) / half_width maps each fitted range onto [-1, 1].
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

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
    x: np.ndarray,
    length: np.ndarray,
    dl_dx: np.ndarray,
    degree: int,
    derivative_weight: float = 1.0,
    hinges: Sequence[tuple[int, float]] = (),
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
        blocks.append(
            derivative_weight
            * np.hstack([monomial_derivatives(x, exponents, var), hinge_derivatives(x, list(hinges), var)])
        )
        targets.append(derivative_weight * dl_dx[:, var])
    a = np.vstack(blocks)
    b = np.concatenate(targets)
    keep = np.isfinite(b)  # derivatives are NaN where the OpenSim path jumped
    a, b = a[keep], b[keep]
    coef, *_ = np.linalg.lstsq(a, b, rcond=None)
    return exponents, coef


class FeatureEvaluator:
    """Fast per-pose evaluation of the shared feature vector [monomials (M), h, h², h³ per hinge, step per hinge].

    Built once per pack. Coordinates that co-occur in some monomial form a block; a block's coordinates are split
    in two halves and each half of two coordinates gets the full table of its power products (11 x 11 for degree
    10), so every feature is ``A.take(i) * A.take(j)`` from one buffer: about eight numpy calls per pose whatever M
    (blocks of more than four coordinates fall back to per-monomial products). Products are associated
    differently from :func:`monomials` (results agree to ~1e-16 relative). Not thread-safe (owns its buffers).
    """

    def __init__(self, exponents: np.ndarray, hinges: list[tuple[int, float]]) -> None:
        exponents = np.asarray(exponents, dtype=np.int64)
        m, n = exponents.shape
        d = int(exponents.max(initial=0))
        self.n, self.degree, self.exponents = n, d, exponents
        self.hinges = [(int(v), float(k)) for v, k in hinges]
        parent = list(range(n))

        def find(a: int) -> int:
            while parent[a] != a:
                parent[a] = parent[parent[a]]
                a = parent[a]
            return a

        for row in exponents:  # blocks: connected components of "appear in the same monomial"
            used = np.flatnonzero(row)
            for a in used[1:]:
                parent[find(int(a))] = find(int(used[0]))
        blocks: dict[int, list[int]] = {}
        for c in sorted({int(c) for row in exponents for c in np.flatnonzero(row)}):
            blocks.setdefault(find(c), []).append(c)
        self.fallback = any(len(cs) > 4 for cs in blocks.values())
        self.n_features = m + 4 * len(self.hinges)
        if self.fallback:
            return
        halves = {r: (cs[: (len(cs) + 1) // 2], cs[(len(cs) + 1) // 2 :]) for r, cs in blocks.items()}
        pairs = sorted({tuple(h) for hs in halves.values() for h in hs if len(h) == 2})
        # buffer layout: power table T (n, d+1) | one (d+1)^2 table per coordinate pair | 3H hinge | H step slots
        n_h, width = len(self.hinges), d + 1
        offset = n * width
        self.buffer = np.zeros(offset + len(pairs) * width * width + 4 * n_h)
        power = self.buffer[:offset].reshape(n, width)
        power[:, 0] = 1.0
        self._power_tail = power[:, 1:]
        self._repeat = np.empty((n, d))
        self._steps = []
        pair_offset = {}
        for k, (a, b) in enumerate(pairs):
            pos = offset + k * width * width
            # table[e_b, e_a] = T[b, e_b] * T[a, e_a]
            self._steps.append(
                (
                    self.buffer[pos : pos + width * width].reshape(width, width),
                    power[b].reshape(-1, 1),
                    power[a].reshape(1, -1),
                )
            )
            pair_offset[(a, b)] = pos
        self._hinge_base = offset + len(pairs) * width * width

        def slot(half: list[int], row: np.ndarray) -> int:
            if not half:
                return 0  # T[0, 0] = 1
            if len(half) == 1:
                return half[0] * width + int(row[half[0]])
            a, b = half
            return pair_offset[(a, b)] + int(row[b]) * width + int(row[a])

        first = np.zeros(m + 4 * n_h, dtype=np.intp)
        second = np.zeros(m + 4 * n_h, dtype=np.intp)
        for i, row in enumerate(exponents):
            nz = np.flatnonzero(row)
            if len(nz):
                h1, h2 = halves[find(int(nz[0]))]
                first[i], second[i] = slot(h1, row), slot(h2, row)
        first[m:] = np.arange(self._hinge_base, self._hinge_base + 4 * n_h)
        self._first, self._second = first, second

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Features (M + 4H,) at normalised pose x (n,): a new array."""
        if self.fallback:
            return np.concatenate(
                [
                    monomials(x[None, :], self.exponents)[0],
                    hinge_values(x[None, :], self.hinges)[0],
                    [float(x[v] > k) for v, k in self.hinges],
                ]
            )
        buf = self.buffer
        if self.degree:
            self._repeat[...] = x[:, None]
            np.multiply.accumulate(self._repeat, axis=1, out=self._power_tail)
        for out, left, right in self._steps:
            np.multiply(left, right, out=out)
        if self.hinges:
            base, n_h = self._hinge_base, len(self.hinges)
            xs = x.tolist()
            for i, (var, knot) in enumerate(self.hinges):
                h = xs[var] - knot
                if h > 0.0:
                    buf[base + 3 * i] = h
                    buf[base + 3 * i + 1] = h * h
                    buf[base + 3 * i + 2] = h * h * h
                    buf[base + 3 * n_h + i] = 1.0
                else:
                    buf[base + 3 * i : base + 3 * i + 3] = 0.0
                    buf[base + 3 * n_h + i] = 0.0
        return buf.take(self._first) * buf.take(self._second)

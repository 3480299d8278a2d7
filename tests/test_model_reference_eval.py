"""The fast per-frame evaluation (ModelPack.frame / moment_arms / mtu_lengths / inverse_dynamics), numpy and
compiled (numba), equals a straightforward evaluation of the pack's stored polynomials and rigid-body description
to 1e-12."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np
import pinocchio as pin
import pytest

from msk_core.errors import ModelError
from msk_core.model import Evaluator, OutOfRange, load_pack
from msk_core.model.poly import (
    FeatureEvaluator,
    hinge_derivatives,
    hinge_values,
    monomial_derivatives,
    monomials,
    total_degree_exponents,
)

PACKS = ["arm26", "bench_press", "deadlift", "lumbar_lift"]


def reference_muscles(pack, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lengths (G,) and moment arms (n, G) from the raw pack JSON: l = C [phi(x), hinges(x)], r = -dl/dq."""
    basis = pack.raw["basis"]
    n = len(pack.coordinates)
    exps = np.asarray(basis["exponents"], dtype=np.int64).reshape(-1, n)
    centre, half = np.asarray(basis["centre"]), np.asarray(basis["half_width"])
    hinges = [(int(v), float(k)) for v, k in basis.get("hinges", [])]
    coef = np.asarray(pack.raw["length_coefficients"], dtype=float).reshape(len(pack.groups), -1)
    x = ((q - centre) / half)[None, :]
    lengths = coef @ np.hstack([monomials(x, exps), hinge_values(x, hinges)])[0]
    arms = np.stack(
        [
            -(coef @ np.hstack([monomial_derivatives(x, exps, j), hinge_derivatives(x, hinges, j)])[0]) / half[j]
            for j in range(n)
        ]
    )
    return lengths, arms


def reference_inverse_dynamics(rigid, dq, qd, qdd, load: float, gravity=None) -> np.ndarray:
    """Pinocchio on the stored description, joint by joint: q_j = gains . dq or f(dq_k) (polyval), virtual work."""
    desc = rigid.description
    qp, vp, ap = rigid.gains @ dq, rigid.gains @ qd, rigid.gains @ qdd
    slopes = {}
    for i, joint in enumerate(desc["joints"]):
        if "function" not in joint:
            continue
        f = joint["function"]
        k, half = f["coordinate"], f["half_width"]
        c = np.polynomial.Polynomial(f["coefficients"])
        x = (dq[k] - f["centre"]) / half
        d1, d2 = c.deriv(1)(x) / half, c.deriv(2)(x) / half**2
        qp[i], vp[i], ap[i] = c(x), d1 * qd[k], d1 * qdd[k] + d2 * qd[k] ** 2
        slopes[i] = (k, d1)
    g = rigid.gravity if gravity is None else np.asarray(gravity, dtype=float)
    model, load_model = pin.Model(rigid.model), pin.Model(rigid.load_model)
    model.gravity.linear = g
    load_model.gravity.linear = g
    tau = pin.rnea(model, model.createData(), qp, vp, ap)
    if load and rigid.n_load_points:
        tau = tau + load * rigid.load_share / rigid.n_load_points / np.linalg.norm(g) * pin.computeGeneralizedGravity(
            load_model, load_model.createData(), qp
        )
    out = np.zeros(len(dq))
    for i in range(len(tau)):
        for k in range(len(dq)):
            out[k] += rigid.torque_scale[k] * rigid.gains[i, k] * tau[i]
        if i in slopes:
            k, d1 = slopes[i]
            out[k] += rigid.torque_scale[k] * d1 * tau[i]
    return out


@pytest.mark.parametrize("evaluator", list(Evaluator))
@pytest.mark.parametrize("name", PACKS)
def test_fast_frame_matches_reference(name, evaluator):
    pack = load_pack(name, evaluator=evaluator)
    rng = np.random.default_rng(11)
    lo, hi = pack.coordinate_ranges[:, 0], pack.coordinate_ranges[:, 1]
    for _ in range(40):
        q = rng.uniform(lo, hi)
        qd, qdd = rng.uniform(-2, 2, len(q)), rng.uniform(-10, 10, len(q))
        load = float(rng.uniform(0, 1000))
        ref_l, ref_r = reference_muscles(pack, q)
        ref_tau = reference_inverse_dynamics(pack.rigid, q - pack.reference_pose, qd, qdd, load)
        lengths, arms, tau = pack.frame(q, qd, qdd, load)
        np.testing.assert_allclose(lengths, ref_l, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(arms, ref_r, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(tau, ref_tau, rtol=1e-12, atol=1e-12 * max(1.0, np.abs(ref_tau).max()))
        # the separate calls agree with the fused one exactly (same code path)
        assert np.array_equal(pack.moment_arms(q), arms) and np.array_equal(pack.mtu_lengths(q), lengths)
        assert np.array_equal(pack.inverse_dynamics(q, qd, qdd, load), tau)
        g = rng.normal(size=3)
        g *= 9.80665 / np.linalg.norm(g)
        np.testing.assert_allclose(
            pack.inverse_dynamics(q, qd, qdd, load, gravity=g),
            reference_inverse_dynamics(pack.rigid, q - pack.reference_pose, qd, qdd, load, g),
            rtol=1e-12,
            atol=1e-12 * max(1.0, np.abs(ref_tau).max()),
        )
    # results are fresh arrays: a later frame never changes an earlier one
    first = pack.frame(lo + 0.25 * (hi - lo), np.zeros(len(lo)), np.zeros(len(lo)), 100.0)
    kept = [a.copy() for a in first]
    pack.frame(lo + 0.75 * (hi - lo), np.ones(len(lo)), np.ones(len(lo)), 500.0)
    assert all(np.array_equal(a, b) for a, b in zip(first, kept))


def test_feature_evaluator_blocks_and_fallback():
    """Blocks of 1-4 co-occurring coordinates use pair tables; a 5-coordinate block falls back; hinges either side."""
    rng = np.random.default_rng(2)
    cases = [
        np.vstack([total_degree_exponents(3, 6), np.zeros((1, 3), dtype=np.int64)]),  # one block of 3
        total_degree_exponents(4, 5),  # one block of 4 (two pair tables)
        np.array([[0, 0, 0, 0, 0], [1, 0, 0, 0, 0], [2, 0, 0, 0, 0], [0, 1, 0, 0, 0], [0, 0, 1, 1, 0]]),  # mixed
        total_degree_exponents(5, 3),  # a block of 5: fallback
    ]
    for exps in cases:
        n = exps.shape[1]
        hinges = [(0, 0.2), (n - 1, -0.4)]
        fe = FeatureEvaluator(exps, hinges)
        assert fe.fallback == (len(exps) == len(total_degree_exponents(5, 3)) and n == 5)
        for _ in range(20):
            x = rng.uniform(-1, 1, n)
            ref = np.concatenate(
                [monomials(x[None], exps)[0], hinge_values(x[None], hinges)[0], [float(x[v] > k) for v, k in hinges]]
            )
            np.testing.assert_allclose(fe(x), ref, rtol=1e-13, atol=1e-15)


@pytest.mark.parametrize("name", PACKS)
def test_compiled_evaluator_matches_numpy_everywhere(name):
    """Every public per-frame call of a compiled pack agrees with the numpy evaluator (1e-12), incl. clamping,
    per-joint torques, the validation model and the out-of-range / shape errors."""
    fast, slow = load_pack(name, evaluator=Evaluator.COMPILED), load_pack(name)
    assert fast.evaluator is Evaluator.COMPILED and slow.evaluator is Evaluator.NUMPY
    rng = np.random.default_rng(5)
    lo, hi = fast.coordinate_ranges[:, 0], fast.coordinate_ranges[:, 1]
    n = len(lo)
    for _ in range(10):
        q = rng.uniform(lo - 0.3, hi + 0.3)  # some coordinates outside their range
        qd, qdd = rng.uniform(-2, 2, n), rng.uniform(-10, 10, n)
        for a, b in zip(
            fast.frame(q, qd, qdd, 300.0, out_of_range=OutOfRange.CLAMP),
            slow.frame(q, qd, qdd, 300.0, out_of_range=OutOfRange.CLAMP),
        ):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * max(1.0, np.abs(b).max()))
        inside = np.clip(q, lo, hi)
        np.testing.assert_allclose(
            fast.mtu_lengths(q, out_of_range=OutOfRange.CLAMP), slow.mtu_lengths(inside), rtol=1e-12, atol=1e-15
        )
        ft, st = fast.joint_torques(inside, qd, qdd, 300.0), slow.joint_torques(inside, qd, qdd, 300.0)
        assert list(ft) == list(st)
        np.testing.assert_allclose(
            list(ft.values()), list(st.values()), rtol=1e-12, atol=1e-12 * max(1.0, np.abs(list(st.values())).max())
        )
        dq = inside - fast.reference_pose
        ref = slow.validation_rigid.inverse_dynamics(dq, qd, qdd, 300.0, None)
        np.testing.assert_allclose(
            fast.validation_rigid.inverse_dynamics(dq, qd, qdd, 300.0, None),
            ref,
            rtol=1e-12,
            atol=1e-12 * max(1.0, np.abs(ref).max()),
        )
        if not fast.in_range(q).all():
            bad = fast.coordinates[int(np.flatnonzero(~fast.in_range(q))[0])]
            for call in (
                lambda q=q, qd=qd, qdd=qdd: fast.frame(q, qd, qdd),
                lambda q=q: fast.moment_arms(q),
                lambda q=q, qd=qd, qdd=qdd: fast.inverse_dynamics(q, qd, qdd),
            ):
                with pytest.raises(ModelError, match=bad):
                    call()
    q = (lo + hi) / 2
    # inputs of any float-convertible kind and layout give the same numbers (no silent re-specialisation)
    column = np.tile(q[:, None], (1, 3))[:, 1]
    assert np.array_equal(fast.moment_arms(column), fast.moment_arms(q))
    assert np.array_equal(fast.moment_arms(q.tolist()), fast.moment_arms(q))
    with pytest.raises(ModelError, match="qd must have shape"):
        fast.frame(q, np.zeros(n + 1), np.zeros(n))
    with pytest.raises(ModelError, match="gravity must be a 3-vector"):
        fast.inverse_dynamics(q, np.zeros(n), np.zeros(n), gravity=[0.0, -9.81])


def test_compiled_evaluator_without_numba_is_a_clear_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "numba", None)  # import numba -> ImportError
    monkeypatch.delitem(sys.modules, "msk_core.model.kernels", raising=False)
    with pytest.raises(ModelError, match="needs numba"):
        load_pack("arm26", evaluator=Evaluator.COMPILED)
    assert load_pack("arm26").evaluator is Evaluator.NUMPY  # the default never needs numba


def test_kernels_compile_in_memory_where_nothing_is_writable(tmp_path):
    """No writable cache location (read-only install, no user cache): numba cannot cache, the kernels compile in
    memory. Simulated root-proof: the module's __pycache__ and the user's ~/.cache are files, not directories."""
    module_dir, home = tmp_path / "pkg", tmp_path / "home"
    module_dir.mkdir()
    home.mkdir()
    (module_dir / "__pycache__").write_text("not a directory")
    (home / ".cache").write_text("not a directory")
    (module_dir / "ro_kernel.py").write_text(
        textwrap.dedent("""
        from msk_core.model.kernels import _jit

        @_jit
        def twice(x):
            return 2.0 * x
    """)
    )
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME")}
    env.update(HOME=str(home), PYTHONPATH=os.pathsep.join([str(module_dir), *sys.path]), PYTHONDONTWRITEBYTECODE="1")
    done = subprocess.run(
        [sys.executable, "-c", "import ro_kernel; print(ro_kernel.twice(21.0), type(ro_kernel.twice._cache).__name__)"],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["42.0", "NullCache"]

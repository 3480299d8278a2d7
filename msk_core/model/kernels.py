"""Compiled (numba) per-frame evaluation of a model pack: one call gives lengths, moment arms and joint torques.

The numpy path spends a frame in ~20 numpy calls and 2 pinocchio calls of 0.4-3 µs each; here the whole frame is
one compiled call over tables built once at pack load (:class:`MuscleTables`, :class:`RigidTables`):

* features: power table of x = (q - centre) / half, monomials as products of table entries, hinges;
* lengths and moment arms: the (lengths + derivative) matrix in CSC form (deadlift: ~10 % non-zero);
* rigid body: recursive Newton-Euler in world coordinates (the same tree, inertias and joint models pinocchio
  builds from the pack; the hand load is a static force on the aggregated load-point masses), the polynomial joints
  (rolling knee) by Horner, torques projected to pack coordinates by virtual work.

Compiled code is cached next to this module (``cache=True``); where that directory and the user cache are not
writable numba cannot cache, and the kernels are compiled in memory at first use instead.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

REVOLUTE, PRISMATIC = 0, 1
# joint_float columns
OFFSET, AXIS, MASS, LEVER, INERTIA, LOAD_MASS, LOAD_LEVER, POLY_CENTRE, POLY_HALF, POLY_SCALE = (
    0,
    3,
    6,
    7,
    10,
    19,
    20,
    23,
    24,
    25,
)
JOINT_FLOAT_COLUMNS = 26
# joint_int columns
PARENT, KIND, POLY_COORD = 0, 1, 2
# pose table rows
LO, HI, CENTRE, HALF, HALF_RANGE, REFERENCE = range(6)


def _jit(fn):
    try:
        return numba.njit(cache=True)(fn)
    except RuntimeError:  # numba found no writable cache location: compile in memory at first call instead
        return numba.njit(fn)


@dataclass(frozen=True)
class MuscleTables:
    """Polynomial length surrogate, flattened into one int64 and one float64 array (one kernel argument each;
    every extra array argument costs ~0.1 µs of dispatch).

    ints: n, G, M, H, rows, nnz, power width | monomial factors (M, n): flat index j * width + exponent into the
    power table | hinge variables (H) | CSC column pointers (M + 4H + 1) | CSC rows (nnz). floats: pose (6, n)
    rows lo, hi, centre, half width, half range, reference pose | hinge knots (H) | CSC values (nnz) | work:
    powers (n, width), features (M + 4H), x, clamped q, dq (3n).

    CSC (feature by feature, scattered into independent rows) rather than CSR: a row-wise dot is one serial
    chain of dependent additions; summation order per row is still ascending feature index."""

    ints: np.ndarray
    floats: np.ndarray
    n: int
    n_groups: int

    @classmethod
    def build(
        cls, *, lo, hi, centre, half, half_range, reference, exponents, hinge_var, hinge_knot, stacked, n_groups: int
    ) -> MuscleTables:
        cols, rows = np.nonzero(stacked.T)  # column-major order: CSC
        indptr = np.searchsorted(cols, np.arange(stacked.shape[1] + 1))
        exponents = np.asarray(exponents, dtype=np.int64)
        m, n = exponents.shape
        n_h = len(hinge_var)
        width = int(exponents.max(initial=0)) + 1
        factors = np.arange(n)[None, :] * width + exponents
        header = [n, n_groups, m, n_h, stacked.shape[0], len(cols), width]
        ints = np.concatenate([header, factors.ravel(), hinge_var, indptr, rows]).astype(np.int64)
        pose = np.vstack([lo, hi, centre, half, half_range, reference]).astype(float)
        work = np.zeros(n * width + stacked.shape[1] + 3 * n)
        floats = np.concatenate([pose.ravel(), np.asarray(hinge_knot, dtype=float), stacked[rows, cols], work])
        return cls(ints=ints, floats=floats, n=n, n_groups=n_groups)


@dataclass(frozen=True)
class RigidTables:
    """Reduced rigid body, flattened like :class:`MuscleTables`.

    ints: J, n, polynomial width | joint_int (J, 3): parent, kind, polynomial coordinate (-1: linear joint).
    floats: load share per load point (0 without load points) | joint_float (J, 26), see the column constants |
    polynomial coefficients (J, width), ascending powers | gains (J, n) | projection (n, J) = gainsᵀ · torque scale
    | work (J * RIGID_WORK)."""

    ints: np.ndarray
    floats: np.ndarray
    n: int
    n_joints: int

    @classmethod
    def build(cls, *, joint_int, joint_float, poly_coef, gains, projection, load_per_point: float) -> RigidTables:
        n_joints, n = gains.shape
        ints = np.concatenate([[n_joints, n, poly_coef.shape[1]], np.asarray(joint_int).ravel()]).astype(np.int64)
        floats = np.concatenate(
            [
                [load_per_point],
                joint_float.ravel(),
                poly_coef.ravel(),
                gains.ravel(),
                projection.ravel(),
                np.zeros(n_joints * RIGID_WORK),
            ]
        )
        return cls(ints=ints, floats=floats.astype(float), n=n, n_joints=n_joints)


RIGID_WORK = 9 + 3 + 4 * 6 + 4  # per joint: rotation, origin, S, v, a, f, then q, v, a, slope


@_jit
def _muscle_views(ints, floats):
    n, n_groups, m, n_h, n_rows, nnz, width = ints[0], ints[1], ints[2], ints[3], ints[4], ints[5], ints[6]
    o = 7
    factors = ints[o : o + m * n].reshape((m, n))
    o += m * n
    hinge_var = ints[o : o + n_h]
    o += n_h
    indptr = ints[o : o + m + 4 * n_h + 1]
    o += m + 4 * n_h + 1
    rows = ints[o : o + nnz]
    pose = floats[: 6 * n].reshape((6, n))
    f = 6 * n
    hinge_knot = floats[f : f + n_h]
    f += n_h
    vals = floats[f : f + nnz]
    f += nnz
    powers = floats[f : f + n * width].reshape((n, width))
    f += n * width
    phi = floats[f : f + m + 4 * n_h]
    f += m + 4 * n_h
    work = floats[f : f + 3 * n]
    return n_groups, n_rows, factors, hinge_var, indptr, rows, pose, hinge_knot, vals, powers, phi, work


@_jit
def muscle_values(x, factors, hinge_var, hinge_knot, indptr, rows, vals, powers, phi, values):
    """values = stacked @ features(x): lengths (G) then moment arms (n × G)."""
    n = x.shape[0]
    degree = powers.shape[1] - 1
    for j in range(n):
        p = 1.0
        powers[j, 0] = 1.0
        for d in range(1, degree + 1):
            p *= x[j]
            powers[j, d] = p
    table = powers.reshape(powers.size)
    m = factors.shape[0]
    for i in range(m):
        v = 1.0
        for j in range(n):  # x_j^0 = 1 exactly: no branch on unused coordinates
            v *= table[factors[i, j]]
        phi[i] = v
    n_h = hinge_var.shape[0]
    for i in range(n_h):
        h = x[hinge_var[i]] - hinge_knot[i]
        if h > 0.0:
            phi[m + 3 * i] = h
            phi[m + 3 * i + 1] = h * h
            phi[m + 3 * i + 2] = h * h * h
            phi[m + 3 * n_h + i] = 1.0
        else:
            phi[m + 3 * i] = 0.0
            phi[m + 3 * i + 1] = 0.0
            phi[m + 3 * i + 2] = 0.0
            phi[m + 3 * n_h + i] = 0.0
    values[:] = 0.0
    for f in range(phi.shape[0]):
        pf = phi[f]
        for k in range(indptr[f], indptr[f + 1]):
            values[rows[k]] += vals[k] * pf


@_jit
def _rigid_views(ints, floats):
    nj, n, width = ints[0], ints[1], ints[2]
    joint_int = ints[3 : 3 + 3 * nj].reshape((nj, 3))
    f = 1
    joint_float = floats[f : f + nj * JOINT_FLOAT_COLUMNS].reshape((nj, JOINT_FLOAT_COLUMNS))
    f += nj * JOINT_FLOAT_COLUMNS
    poly_coef = floats[f : f + nj * width].reshape((nj, width))
    f += nj * width
    gains = floats[f : f + nj * n].reshape((nj, n))
    f += nj * n
    projection = floats[f : f + n * nj].reshape((n, nj))
    f += n * nj
    work = floats[f : f + nj * RIGID_WORK]
    return floats[0], joint_int, joint_float, poly_coef, gains, projection, work


@_jit
def _world_inertia_times(body, r, x, y, z):
    """R I_c Rᵀ v: the body's inertia about its centre of mass (``body[INERTIA:INERTIA + 9]``, body axes, row-major)
    times the world vector v = (x, y, z), in world axes (``r``: the body's rotation, body to world)."""
    bx = r[0, 0] * x + r[1, 0] * y + r[2, 0] * z  # Rᵀ v: v in body axes
    by = r[0, 1] * x + r[1, 1] * y + r[2, 1] * z
    bz = r[0, 2] * x + r[1, 2] * y + r[2, 2] * z
    tx = body[INERTIA] * bx + body[INERTIA + 1] * by + body[INERTIA + 2] * bz
    ty = body[INERTIA + 3] * bx + body[INERTIA + 4] * by + body[INERTIA + 5] * bz
    tz = body[INERTIA + 6] * bx + body[INERTIA + 7] * by + body[INERTIA + 8] * bz
    return (
        r[0, 0] * tx + r[0, 1] * ty + r[0, 2] * tz,
        r[1, 0] * tx + r[1, 1] * ty + r[1, 2] * tz,
        r[2, 0] * tx + r[2, 1] * ty + r[2, 2] * tz,
    )


@_jit
def rigid_torques(dq, qd, qdd, hand_load, gravity, ints, floats, tau, tau_joint):
    """Inverse dynamics: tau (n,) per pack coordinate, tau_joint (J,) per reduced-model joint (incl. the hand load)."""
    load_per_point, joint_int, joint_float, poly_coef, gains, projection, work = _rigid_views(ints, floats)
    nj = joint_int.shape[0]
    n = dq.shape[0]
    rot = work[: 9 * nj].reshape((nj, 3, 3))
    w0 = 9 * nj
    pos = work[w0 : w0 + 3 * nj].reshape((nj, 3))
    w0 += 3 * nj
    motion = work[w0 : w0 + 6 * nj].reshape((nj, 6))  # joint motion subspace S (angular, linear), world, origin
    w0 += 6 * nj
    vel = work[w0 : w0 + 6 * nj].reshape((nj, 6))
    w0 += 6 * nj
    acc = work[w0 : w0 + 6 * nj].reshape((nj, 6))
    w0 += 6 * nj
    force = work[w0 : w0 + 6 * nj].reshape((nj, 6))
    w0 += 6 * nj
    qj = work[w0 : w0 + nj]
    vj = work[w0 + nj : w0 + 2 * nj]
    aj = work[w0 + 2 * nj : w0 + 3 * nj]
    slope = work[w0 + 3 * nj : w0 + 4 * nj]  # f'(q) of polynomial joints (read only for those)
    for i in range(nj):
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        for k in range(n):
            g = gains[i, k]
            s0 += g * dq[k]
            s1 += g * qd[k]
            s2 += g * qdd[k]
        k = joint_int[i, POLY_COORD]
        if k >= 0:  # q_j = f(x), x = (dq_k - centre) / half: Horner for f, f', f''
            coef = poly_coef[i]
            deg = coef.shape[0] - 1
            half = joint_float[i, POLY_HALF]
            x = (dq[k] - joint_float[i, POLY_CENTRE]) / half
            f = coef[deg]
            for d in range(deg - 1, -1, -1):
                f = f * x + coef[d]
            d1 = deg * coef[deg]
            for d in range(deg - 1, 0, -1):
                d1 = d1 * x + d * coef[d]
            d2 = deg * (deg - 1) * coef[deg]
            for d in range(deg - 1, 1, -1):
                d2 = d2 * x + d * (d - 1) * coef[d]
            f1 = d1 / half
            f2 = d2 / (half * half)
            s0 = f
            s1 = f1 * qd[k]
            s2 = f1 * qdd[k] + f2 * qd[k] * qd[k]
            slope[i] = joint_float[i, POLY_SCALE] * f1
        qj[i] = s0
        vj[i] = s1
        aj[i] = s2
    g_norm = math.sqrt(gravity[0] * gravity[0] + gravity[1] * gravity[1] + gravity[2] * gravity[2])
    load_scale = hand_load * load_per_point / (g_norm if g_norm > 0.0 else 1.0)
    gx, gy, gz = gravity[0], gravity[1], gravity[2]
    for i in range(nj):
        par = joint_int[i, PARENT]
        # parent pose, velocity, acceleration (root: ground, accelerating against gravity)
        if par >= 0:
            p00, p01, p02 = rot[par, 0, 0], rot[par, 0, 1], rot[par, 0, 2]
            p10, p11, p12 = rot[par, 1, 0], rot[par, 1, 1], rot[par, 1, 2]
            p20, p21, p22 = rot[par, 2, 0], rot[par, 2, 1], rot[par, 2, 2]
            ox, oy, oz = pos[par, 0], pos[par, 1], pos[par, 2]
            wx, wy, wz, vx, vy, vz = vel[par, 0], vel[par, 1], vel[par, 2], vel[par, 3], vel[par, 4], vel[par, 5]
            alx, aly, alz, aox, aoy, aoz = acc[par, 0], acc[par, 1], acc[par, 2], acc[par, 3], acc[par, 4], acc[par, 5]
        else:
            p00, p01, p02, p10, p11, p12, p20, p21, p22 = 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0
            ox, oy, oz = 0.0, 0.0, 0.0
            wx, wy, wz, vx, vy, vz = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
            alx, aly, alz, aox, aoy, aoz = 0.0, 0.0, 0.0, -gx, -gy, -gz
        bx, by, bz = joint_float[i, OFFSET], joint_float[i, OFFSET + 1], joint_float[i, OFFSET + 2]
        ax, ay, az = joint_float[i, AXIS], joint_float[i, AXIS + 1], joint_float[i, AXIS + 2]
        ox += p00 * bx + p01 * by + p02 * bz
        oy += p10 * bx + p11 * by + p12 * bz
        oz += p20 * bx + p21 * by + p22 * bz
        ux = p00 * ax + p01 * ay + p02 * az
        uy = p10 * ax + p11 * ay + p12 * az
        uz = p20 * ax + p21 * ay + p22 * az
        if joint_int[i, KIND] == REVOLUTE:
            # R_i = R_parent @ rot(axis, q), rot = cI + s[axis]x + (1 - c) axis axisᵀ; S = (u, o x u)
            cq, sq = math.cos(qj[i]), math.sin(qj[i])
            cc = 1.0 - cq
            j00, j01, j02 = cq + cc * ax * ax, cc * ax * ay - sq * az, cc * ax * az + sq * ay
            j10, j11, j12 = cc * ay * ax + sq * az, cq + cc * ay * ay, cc * ay * az - sq * ax
            j20, j21, j22 = cc * az * ax - sq * ay, cc * az * ay + sq * ax, cq + cc * az * az
            r00, r01, r02 = (
                p00 * j00 + p01 * j10 + p02 * j20,
                p00 * j01 + p01 * j11 + p02 * j21,
                p00 * j02 + p01 * j12 + p02 * j22,
            )
            r10, r11, r12 = (
                p10 * j00 + p11 * j10 + p12 * j20,
                p10 * j01 + p11 * j11 + p12 * j21,
                p10 * j02 + p11 * j12 + p12 * j22,
            )
            r20, r21, r22 = (
                p20 * j00 + p21 * j10 + p22 * j20,
                p20 * j01 + p21 * j11 + p22 * j21,
                p20 * j02 + p21 * j12 + p22 * j22,
            )
            s0, s1, s2 = ux, uy, uz
            s3, s4, s5 = oy * uz - oz * uy, oz * ux - ox * uz, ox * uy - oy * ux
        else:
            ox += ux * qj[i]
            oy += uy * qj[i]
            oz += uz * qj[i]
            r00, r01, r02, r10, r11, r12, r20, r21, r22 = p00, p01, p02, p10, p11, p12, p20, p21, p22
            s0, s1, s2, s3, s4, s5 = 0.0, 0.0, 0.0, ux, uy, uz
        # v_i = v_p + S qd; a_i = a_p + S qdd + v_i x (S qd)
        qdi, qddi = vj[i], aj[i]
        wx += s0 * qdi
        wy += s1 * qdi
        wz += s2 * qdi
        vx += s3 * qdi
        vy += s4 * qdi
        vz += s5 * qdi
        m0, m1, m2, m3, m4, m5 = s0 * qdi, s1 * qdi, s2 * qdi, s3 * qdi, s4 * qdi, s5 * qdi
        alx += s0 * qddi + (wy * m2 - wz * m1)
        aly += s1 * qddi + (wz * m0 - wx * m2)
        alz += s2 * qddi + (wx * m1 - wy * m0)
        aox += s3 * qddi + (wy * m5 - wz * m4) + (vy * m2 - vz * m1)
        aoy += s4 * qddi + (wz * m3 - wx * m5) + (vz * m0 - vx * m2)
        aoz += s5 * qddi + (wx * m4 - wy * m3) + (vx * m1 - vy * m0)
        rot[i, 0, 0], rot[i, 0, 1], rot[i, 0, 2] = r00, r01, r02
        rot[i, 1, 0], rot[i, 1, 1], rot[i, 1, 2] = r10, r11, r12
        rot[i, 2, 0], rot[i, 2, 1], rot[i, 2, 2] = r20, r21, r22
        pos[i, 0], pos[i, 1], pos[i, 2] = ox, oy, oz
        motion[i, 0], motion[i, 1], motion[i, 2], motion[i, 3], motion[i, 4], motion[i, 5] = s0, s1, s2, s3, s4, s5
        vel[i, 0], vel[i, 1], vel[i, 2], vel[i, 3], vel[i, 4], vel[i, 5] = wx, wy, wz, vx, vy, vz
        acc[i, 0], acc[i, 1], acc[i, 2], acc[i, 3], acc[i, 4], acc[i, 5] = alx, aly, alz, aox, aoy, aoz
        f0, f1, f2, f3, f4, f5 = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        mass = joint_float[i, MASS]
        if mass != 0.0:
            lx, ly, lz = joint_float[i, LEVER], joint_float[i, LEVER + 1], joint_float[i, LEVER + 2]
            cx = ox + r00 * lx + r01 * ly + r02 * lz
            cy = oy + r10 * lx + r11 * ly + r12 * lz
            cz = oz + r20 * lx + r21 * ly + r22 * lz
            iwx, iwy, iwz = _world_inertia_times(joint_float[i], rot[i], wx, wy, wz)  # I_c w in world axes
            iax, iay, iaz = _world_inertia_times(joint_float[i], rot[i], alx, aly, alz)  # I_c alpha in world axes
            # momentum h = I v: linear m (v_o + w x c), angular I_c w + c x h_lin; f = I a + v x* h
            hlx = mass * (vx + (wy * cz - wz * cy))
            hly = mass * (vy + (wz * cx - wx * cz))
            hlz = mass * (vz + (wx * cy - wy * cx))
            hax = iwx + (cy * hlz - cz * hly)
            hay = iwy + (cz * hlx - cx * hlz)
            haz = iwz + (cx * hly - cy * hlx)
            flx = mass * (aox + (aly * cz - alz * cy))
            fly = mass * (aoy + (alz * cx - alx * cz))
            flz = mass * (aoz + (alx * cy - aly * cx))
            f0 = iax + (cy * flz - cz * fly) + (wy * haz - wz * hay) + (vy * hlz - vz * hly)
            f1 = iay + (cz * flx - cx * flz) + (wz * hax - wx * haz) + (vz * hlx - vx * hlz)
            f2 = iaz + (cx * fly - cy * flx) + (wx * hay - wy * hax) + (vx * hly - vy * hlx)
            f3 = flx + (wy * hlz - wz * hly)
            f4 = fly + (wz * hlx - wx * hlz)
            f5 = flz + (wx * hly - wy * hlx)
        load_mass = joint_float[i, LOAD_MASS] * load_scale
        if load_mass != 0.0:  # static hand load: the force holding load_mass against gravity at the load points
            lx, ly, lz = joint_float[i, LOAD_LEVER], joint_float[i, LOAD_LEVER + 1], joint_float[i, LOAD_LEVER + 2]
            cx = ox + r00 * lx + r01 * ly + r02 * lz
            cy = oy + r10 * lx + r11 * ly + r12 * lz
            cz = oz + r20 * lx + r21 * ly + r22 * lz
            flx, fly, flz = -gx * load_mass, -gy * load_mass, -gz * load_mass
            f0 += cy * flz - cz * fly
            f1 += cz * flx - cx * flz
            f2 += cx * fly - cy * flx
            f3 += flx
            f4 += fly
            f5 += flz
        force[i, 0], force[i, 1], force[i, 2], force[i, 3], force[i, 4], force[i, 5] = f0, f1, f2, f3, f4, f5
    for i in range(nj - 1, -1, -1):
        t = 0.0
        for a in range(6):
            t += motion[i, a] * force[i, a]
        tau_joint[i] = t
        par = joint_int[i, PARENT]
        if par >= 0:
            for a in range(6):
                force[par, a] += force[i, a]
    for k in range(n):
        s = 0.0
        for i in range(nj):
            p = slope[i] if joint_int[i, POLY_COORD] == k else projection[k, i]
            s += p * tau_joint[i]
        tau[k] = s


MUSCLES, DYNAMICS, CLAMP = 1, 2, 4  # frame() mode bits


@_jit
def frame(q, qd, qdd, hand_load, gravity, mode, muscle_ints, muscle_floats, rigid_ints, rigid_floats, out):
    """One frame into out: lengths (G) and moment arms (n × G) if mode & MUSCLES, then tau (n) and tau per joint (J)
    if mode & DYNAMICS. Returns False (nothing evaluated) when mode has no CLAMP and q is outside the fitted ranges.
    """
    n_groups, n_rows, factors, hinge_var, indptr, rows, pose, hinge_knot, vals, powers, phi, work = _muscle_views(
        muscle_ints, muscle_floats
    )
    n = q.shape[0]
    x = work[:n]
    qc = work[n : 2 * n]
    dq = work[2 * n : 3 * n]
    for j in range(n):
        v = q[j]
        if mode & CLAMP:
            v = min(max(v, pose[LO, j]), pose[HI, j])
        else:
            offset = v - pose[CENTRE, j]
            if offset > pose[HALF_RANGE, j] or -offset > pose[HALF_RANGE, j]:
                return False
        qc[j] = v
    base = 0
    if mode & MUSCLES:
        for j in range(n):
            x[j] = (qc[j] - pose[CENTRE, j]) / pose[HALF, j]
        muscle_values(x, factors, hinge_var, hinge_knot, indptr, rows, vals, powers, phi, out[:n_rows])
        base = n_rows
    if mode & DYNAMICS:
        for j in range(n):
            dq[j] = qc[j] - pose[REFERENCE, j]
        nj = rigid_ints[0]
        rigid_torques(
            dq,
            qd,
            qdd,
            hand_load,
            gravity,
            rigid_ints,
            rigid_floats,
            out[base : base + n],
            out[base + n : base + n + nj],
        )
    return True


@_jit
def rigid(dq, qd, qdd, hand_load, gravity, ints, floats, out):
    """Inverse dynamics at offsets dq = q - q_ref into out: tau (n), then tau per joint (J)."""
    n = dq.shape[0]
    rigid_torques(dq, qd, qdd, hand_load, gravity, ints, floats, out[:n], out[n:])

"""Validate a pack against OpenSim on fresh random poses (never the fitting poses: a different random stream)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from msk_core.model import osim_tools
from msk_core.model.pack import ModelPack
from msk_core.model.spec import parse_spec
from msk_core.progress import Progress, counted

CHECK_SEED_OFFSET = 7919  # keeps check poses independent of the fit's Latin hypercube


def random_poses(pack: ModelPack, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed + CHECK_SEED_OFFSET)
    lo, hi = pack.coordinate_ranges[:, 0], pack.coordinate_ranges[:, 1]
    return rng.uniform(lo, hi, size=(n, len(lo)))


def check_muscles(
    pack: ModelPack, osim_path: str | Path, *, n_poses: int = 30, seed: int = 0, progress: Progress | None = None
) -> dict:
    """Group moment arms (vs OpenSim computeMomentArm, F_max-weighted like the pack) and lengths."""
    spec = parse_spec(pack.raw["spec"])
    model, state = osim_tools.load_model(osim_path, gravity=spec.dynamics.gravity)
    poser = osim_tools.OsimPoser(model, state, spec)
    names = [m for g in pack.groups for m in pack.members[g]]
    weights = np.zeros((len(pack.groups), len(names)))
    col = 0
    for gi, g in enumerate(pack.groups):
        forces = np.array([pack.member_f_max[m] for m in pack.members[g]])
        weights[gi, col : col + len(forces)] = forces / forces.sum()
        col += len(forces)
    poses = random_poses(pack, n_poses, seed)
    ref_r, fit_r, ref_l, fit_l, fd_r = [], [], [], [], []
    glitches = 0
    delta = 1e-5
    for q in counted(poses, progress, f"{pack.name}: OpenSim moment arms (poses)"):
        bad = osim_tools.opensim_glitches(poser, names, q)
        glitches += int(bad.any())
        group_bad = (weights[:, bad].sum(axis=1) > 0)[:, None]
        ref_r.append(np.where(group_bad, np.nan, weights @ osim_tools.opensim_moment_arms(poser, names, q)))  # (G, n)
        ref_l.append(np.where(group_bad[:, 0], np.nan, weights @ osim_tools.opensim_lengths(poser, names, q)))
        # second reference: -dl/dq of OpenSim's own path length (computeMomentArm can pick another wrap solution)
        fd = np.zeros((len(pack.groups), len(q)))
        for j in range(len(q)):
            e = np.zeros(len(q))
            e[j] = delta
            plus = osim_tools.opensim_lengths(poser, names, q + e)
            minus = osim_tools.opensim_lengths(poser, names, q - e)
            fd[:, j] = -(weights @ (plus - minus)) / (2 * delta)
        fd_r.append(np.where(group_bad, np.nan, fd))
        fit_r.append(pack.moment_arms(q).T)
        fit_l.append(pack.mtu_lengths(q))
    opensim_arms, pack_arms = np.array(ref_r), np.array(fit_r)  # (S, G, n)
    err_r = (pack_arms - opensim_arms) * 1e3
    err_fd = (pack_arms - np.array(fd_r)) * 1e3
    err_l = (np.array(fit_l) - np.array(ref_l)) * 1e3
    mean, peak = np.nanmean, np.nanmax
    per_group = {}
    for gi, g in enumerate(pack.groups):
        per_group[g] = {
            "moment_arm_rms_mm": {
                c: float(np.sqrt(mean(err_r[:, gi, j] ** 2))) for j, c in enumerate(pack.coordinates)
            },
            "moment_arm_max_mm": {c: float(peak(np.abs(err_r[:, gi, j]))) for j, c in enumerate(pack.coordinates)},
            "length_rms_mm": float(np.sqrt(mean(err_l[:, gi] ** 2))),
            "path_derivative_max_mm": {
                c: float(peak(np.abs(err_fd[:, gi, j]))) for j, c in enumerate(pack.coordinates)
            },
            "length_max_mm": float(peak(np.abs(err_l[:, gi]))),
        }
    return {
        "poses": n_poses,
        "opensim_glitch_poses_excluded": glitches,
        "moment_arm_rms_mm": float(np.sqrt(mean(err_r**2))),
        "moment_arm_max_mm": float(peak(np.abs(err_r))),
        "length_rms_mm": float(np.sqrt(mean(err_l**2))),
        "length_max_mm": float(peak(np.abs(err_l))),
        "path_derivative_rms_mm": float(np.sqrt(mean(err_fd**2))),
        "path_derivative_max_mm": float(peak(np.abs(err_fd))),
        "groups": per_group,
        "opensim_moment_arms": opensim_arms,
        "pack_moment_arms": pack_arms,
    }


def check_dynamics(
    pack: ModelPack,
    osim_path: str | Path,
    *,
    n_poses: int = 30,
    seed: int = 0,
    hand_load: float = 200.0,
    progress: Progress | None = None,
) -> dict:
    """Reduced inverse dynamics (the pack's ground-rooted validation model) vs OpenSim's InverseDynamicsSolver.

    Same locked coordinates, couplings, gravity and hand load; random q, qd (±1 rad/s), qdd (±10 rad/s²).
    """
    spec = parse_spec(pack.raw["spec"])
    if not spec.dynamics.has_hand_load:
        hand_load = 0.0  # a pack without load points takes none (a walk: the ground's forces are in its ID file)
    model, _ = osim_tools.load_model(osim_path, gravity=spec.dynamics.gravity, forces=False)
    g = np.array(model.getGravity().to_numpy())
    redirect = {}
    if spec.dynamics.hanging:
        # the same pendulum arms as the pack: pivots at the reference pose (hanging bodies' joints are locked)
        poser = osim_tools.OsimPoser(model, model.initSystem(), spec)
        poser.set(pack.reference_pose)
        redirect = osim_tools.hang_subtrees(model, poser.state, spec)
    osim_tools.add_hand_loads(model, spec, hand_load, g, pack.validation_rigid.load_share, redirect)
    state = model.initSystem()
    poser = osim_tools.OsimPoser(model, state, spec)
    rng = np.random.default_rng(seed + 2 * CHECK_SEED_OFFSET)
    poses = random_poses(pack, n_poses, seed + 1)
    opensim_tau, pack_tau = [], []
    rigid = pack.validation_rigid
    for q in counted(poses, progress, f"{pack.name}: OpenSim inverse dynamics (poses)"):
        qd = rng.uniform(-1, 1, len(q))
        qdd = rng.uniform(-10, 10, len(q))
        opensim_tau.append(osim_tools.opensim_inverse_dynamics(poser, q, qd, qdd))
        pack_tau.append(rigid.inverse_dynamics(q - pack.reference_pose, qd, qdd, hand_load, None))
    ref, fit = np.array(opensim_tau), np.array(pack_tau)
    return {
        "poses": n_poses,
        "hand_load_newton": hand_load,
        "pack_has_hand_load": spec.dynamics.has_hand_load,
        **_torque_errors(pack, ref, fit),
        "opensim": ref,
        "pack": fit,
    }


def check_hanging_static(
    pack: ModelPack,
    osim_path: str | Path,
    *,
    swing: dict[str, str],
    n_poses: int = 20,
    seed: int = 0,
    hand_load: float = 600.0,
) -> dict:
    """How good is the pendulum assumption (``[dynamics] hanging``)? Static OpenSim ID with the real arm bodies.

    At random static poses (qd = qdd = 0) each hanging subtree keeps its own bodies and masses in OpenSim, and its
    ``swing`` coordinate (pivot body -> coordinate, e.g. ``{"humerus_r": "elv_angle_r"}``) is solved so that the
    load point hangs plumb below the pivot (same horizontal position along the model's ground x, the sagittal
    direction); the bar acts at the real hand load points. Compared with the pack's validation model (point masses
    and bar at the pivots). The residual difference is the arms' centres of mass being off the pivot-hand line and
    out-of-plane (the shoulder flexion coordinate is not exactly sagittal).
    """
    from scipy.optimize import brentq  # noqa: PLC0415

    spec = parse_spec(pack.raw["spec"])
    model, _ = osim_tools.load_model(osim_path, gravity=spec.dynamics.gravity, forces=False)
    g = np.array(model.getGravity().to_numpy())
    osim_tools.add_hand_loads(model, spec, hand_load, g, pack.validation_rigid.load_share)
    state = model.initSystem()
    poser = osim_tools.OsimPoser(model, state, spec)
    bodies = model.getBodySet()
    horizontal = np.array([1.0, 0.0, 0.0])
    loads = {lp.body: lp for lp in spec.dynamics.load_points}
    hand_of = {}
    for pivot in swing:
        subtree = set(osim_tools._subtree(model, pivot))
        hand_of[pivot] = next(b for b in loads if b in subtree)
    poses = random_poses(pack, n_poses, seed + 2)
    opensim_tau, pack_tau, angles = [], [], []
    zeros = np.zeros(len(pack.coordinates))
    for q in poses:
        poser.set(q)
        solved = {}
        for pivot, coord in swing.items():
            lp = loads[hand_of[pivot]]

            def offset(value: float, coord: str = coord, pivot: str = pivot, lp=lp) -> float:
                poser.coords[coord].setValue(poser.state, value, False)
                model.realizePosition(poser.state)
                hand = (
                    bodies.get(lp.body).findStationLocationInGround(poser.state, poser._osim.Vec3(*lp.point)).to_numpy()
                )
                return float(
                    horizontal @ (np.array(hand) - bodies.get(pivot).getPositionInGround(poser.state).to_numpy())
                )

            solved[coord] = brentq(offset, -1.5, 1.5, xtol=1e-10)
        poser.base.update(solved)
        opensim_tau.append(osim_tools.opensim_inverse_dynamics(poser, q, zeros, zeros))
        pack_tau.append(pack.validation_rigid.inverse_dynamics(q - pack.reference_pose, zeros, zeros, hand_load, None))
        angles.append([np.degrees(v) for v in solved.values()])
    return {
        "poses": n_poses,
        "hand_load_newton": hand_load,
        "swing_deg_range": [float(np.min(angles)), float(np.max(angles))],
        **_torque_errors(pack, np.array(opensim_tau), np.array(pack_tau)),
    }


def _torque_errors(pack: ModelPack, ref: np.ndarray, fit: np.ndarray) -> dict[str, dict[str, float]]:
    """Per coordinate: OpenSim's peak torque over the poses (rows of ``ref``), the pack's largest error (``fit``)
    in N·m and in % of that peak."""
    peak = np.max(np.abs(ref), axis=0)
    err = np.abs(fit - ref)
    return {
        "peak_nm": dict(zip(pack.coordinates, peak.tolist())),
        "max_error_nm": dict(zip(pack.coordinates, err.max(axis=0).tolist())),
        "max_error_percent_of_peak": dict(zip(pack.coordinates, (100 * err.max(axis=0) / peak).tolist())),
    }

"""The lower-limb pack (gait2392, right leg) against OpenSim over the real walk's range of motion.

Targets (issue 29): moment arms within 0.5 mm RMS of OpenSim's, inverse dynamics of the walk's coordinates within 1 %
of OpenSim's. Poses: fresh random ones inside the pack ranges (the walk's range of motion plus a margin) and frames
of the walk itself (``../shared/data/lowerlimb-walk/walk45_ik.sto``).
"""

from __future__ import annotations

import numpy as np
import pytest

from msk_core.io import read_sto
from msk_core.model import load_pack

pytestmark = [pytest.mark.needs_shared]

EMG_MUSCLES = [
    "soleus_r",
    "med_gas_r",
    "lat_gas_r",
    "tib_ant_r",
    "semimem_r",
    "bifemlh_r",
    "vas_lat_r",
    "rect_fem_r",
    "vas_med_r",
]
COORDS = ["hip_flexion_r", "hip_adduction_r", "hip_rotation_r", "knee_angle_r", "ankle_angle_r"]


def _walk_frames(shared_dir, every: int):
    """(time, q rad, qd, qdd) of the walk's pack coordinates, every ``every``-th frame (derivatives on all frames)."""
    ik = read_sto(shared_dir / "data" / "lowerlimb-walk" / "walk45_ik.sto")
    q = np.radians(ik.select(COORDS))
    qd = np.gradient(q, ik.time, axis=0)
    qdd = np.gradient(qd, ik.time, axis=0)
    sel = slice(5, None, every)
    return ik.time[sel], q[sel], qd[sel], qdd[sel]


def test_groups_are_the_models_right_leg_muscles_with_the_emg_names(shared_dir):
    pack = load_pack("gait2392")
    assert pack.coordinates == COORDS
    emg = read_sto(shared_dir / "data" / "lowerlimb-walk" / "walk45_emgFilt.sto")
    assert emg.columns == EMG_MUSCLES and set(EMG_MUSCLES) <= set(pack.groups)
    assert len(pack.groups) == 43 and all(pack.members[g] == [g] for g in pack.groups)
    # the walk lies inside the fitted ranges: no frame is clamped
    _, q, _, _ = _walk_frames(shared_dir, 1)
    assert np.all((q >= pack.coordinate_ranges[:, 0]) & (q <= pack.coordinate_ranges[:, 1]))
    assert pack.rigid.n_load_points == 0 and not pack.raw["dynamics"]["load_points"]  # no hand load


@pytest.mark.needs_opensim
def test_moment_arms_vs_opensim_over_the_walks_range_of_motion(shared_dir):
    pytest.importorskip("opensim")
    from msk_core.model import osim_tools  # noqa: PLC0415
    from msk_core.model.check import check_muscles  # noqa: PLC0415
    from msk_core.model.spec import parse_spec  # noqa: PLC0415

    pack = load_pack("gait2392")
    osim = shared_dir / "models" / "gait2392.osim"
    report = check_muscles(pack, osim, n_poses=12, seed=29)
    worst_group = max(report["groups"], key=lambda g: max(report["groups"][g]["moment_arm_rms_mm"].values()))
    print(
        f"random poses: moment arms RMS {report['moment_arm_rms_mm']:.3f} mm, max {report['moment_arm_max_mm']:.3f} "
        f"mm (worst group {worst_group})"
    )
    assert report["moment_arm_rms_mm"] < 0.5
    assert report["opensim_glitch_poses_excluded"] <= 2
    for group, stats in report["groups"].items():
        assert max(stats["moment_arm_rms_mm"].values()) < 1.0, (group, stats)
    # frames of the walk itself, the model posed as the pack poses it (pelvis, subtalar, mtp locked)
    model, state = osim_tools.load_model(osim)
    poser = osim_tools.OsimPoser(model, state, parse_spec(pack.raw["spec"]))
    _, frames, _, _ = _walk_frames(shared_dir, 197)
    errors = []
    for q in frames:
        reference = osim_tools.opensim_moment_arms(poser, pack.groups, q)  # (groups, coordinates): one muscle each
        errors.append(pack.moment_arms(q).T - reference)
    errors = 1e3 * np.array(errors)
    rms = float(np.sqrt(np.mean(errors**2)))
    print(f"{len(frames)} walk frames: moment arms RMS {rms:.3f} mm, max {np.abs(errors).max():.3f} mm")
    assert rms < 0.5


@pytest.mark.needs_opensim
def test_inverse_dynamics_of_the_walks_coordinates_vs_opensim(shared_dir):
    pytest.importorskip("opensim")
    from msk_core.model import osim_tools  # noqa: PLC0415
    from msk_core.model.check import check_dynamics  # noqa: PLC0415
    from msk_core.model.spec import parse_spec  # noqa: PLC0415

    pack = load_pack("gait2392")
    osim = shared_dir / "models" / "gait2392.osim"
    report = check_dynamics(pack, osim, n_poses=10, seed=29, hand_load=0.0)
    for coord, pct in report["max_error_percent_of_peak"].items():
        assert pct < 1.0, (coord, report["max_error_percent_of_peak"])
    # the walk's own coordinates, velocities and accelerations: the right leg's motion below a fixed pelvis
    model, _ = osim_tools.load_model(osim, forces=False)
    poser = osim_tools.OsimPoser(model, model.initSystem(), parse_spec(pack.raw["spec"]))
    _, q, qd, qdd = _walk_frames(shared_dir, 59)
    ref = np.array([osim_tools.opensim_inverse_dynamics(poser, *frame) for frame in zip(q, qd, qdd)])
    mine = np.array([pack.inverse_dynamics(*frame) for frame in zip(q, qd, qdd)])
    peak = np.abs(ref).max(axis=0)
    pct = 100 * np.abs(mine - ref).max(axis=0) / peak
    print(f"{len(q)} walk frames: max error % of peak " + ", ".join(f"{c} {p:.4f}" for c, p in zip(COORDS, pct)))
    assert np.all(pct < 1.0), dict(zip(COORDS, pct))


def test_compiled_and_numpy_evaluators_agree_on_the_walk(shared_dir):
    """The rolling knee is a polynomial chain and 43 groups a wide sparse table: both evaluators give one answer."""
    pytest.importorskip("numba")
    from msk_core.model import Evaluator  # noqa: PLC0415

    numpy_pack, fast = load_pack("gait2392"), load_pack("gait2392", evaluator=Evaluator.COMPILED)
    _, q, qd, qdd = _walk_frames(shared_dir, 97)
    for frame in zip(q, qd, qdd):
        lengths, r, tau = fast.frame(*frame)
        lengths_np, r_np, tau_np = numpy_pack.frame(*frame)
        np.testing.assert_allclose(lengths, lengths_np, rtol=0, atol=1e-12)
        np.testing.assert_allclose(r, r_np, rtol=0, atol=1e-12)
        np.testing.assert_allclose(tau, tau_np, rtol=0, atol=1e-9 * max(1.0, np.abs(tau_np).max()))

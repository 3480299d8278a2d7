"""Compare a pack's inverse dynamics with a recorded OpenSim inverse-dynamics result (IK + ID .sto files).

The pack's model is rooted at its locked pelvis, so each frame's pelvis orientation (from the IK file, through
OpenSim) enters as the gravity vector expressed in the pelvis frame, with the pelvis origin's linear acceleration
folded in (g - a); the pelvis' angular velocity/acceleration is neglected (documented). Pack coordinate
velocities/accelerations come from a smoothing spline of the IK angles.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.interpolate import make_smoothing_spline

from msk_core.errors import FileFormatError
from msk_core.model import osim_tools
from msk_core.model.pack import ModelPack, OutOfRange


def read_sto(path: str | Path) -> tuple[list[str], np.ndarray, bool]:
    """(column names, data, in_degrees) of an OpenSim .sto/.mot table."""
    path = Path(path)
    lines = path.read_text().splitlines()
    try:
        end = next(i for i, line in enumerate(lines) if line.strip().lower() == "endheader")
    except StopIteration:
        raise FileFormatError("no 'endheader' line", path=path) from None
    in_degrees = any(line.replace(" ", "").lower() == "indegrees=yes" for line in lines[:end])
    names = lines[end + 1].split()
    rows = []
    for number, line in enumerate(lines[end + 2 :], start=end + 3):
        if not line.strip():
            continue
        try:
            rows.append([float(v) for v in line.split()])
        except ValueError as exc:
            raise FileFormatError(f"not a number: {exc}", path=path, line=number) from None
        if len(rows[-1]) != len(names):
            raise FileFormatError(f"expected {len(names)} columns, got {len(rows[-1])}", path=path, line=number)
    return names, np.array(rows), in_degrees


def compare_with_recorded_id(
    pack: ModelPack,
    osim_path: str | Path,
    ik_path: str | Path,
    id_path: str | Path,
    *,
    hand_load_newton: float,
    root_body: str = "pelvis",
    include_root_acceleration: bool = True,
) -> dict:
    """Pack torques vs the recorded ID column of each pack coordinate, frame by frame."""
    ik_names, ik, ik_deg = read_sto(ik_path)
    id_names, idd, _ = read_sto(id_path)
    if ik_deg:
        ik[:, 1:] = np.radians(ik[:, 1:])
    model, state = osim_tools.load_model(osim_path)
    coords = model.getCoordinateSet()
    root = model.getBodySet().get(root_body)
    g_world = np.array(model.getGravity().to_numpy())
    t = ik[:, 0] - ik[0, 0]
    q = np.stack([ik[:, ik_names.index(c)] for c in pack.coordinates], axis=1)
    qd = np.zeros_like(q)
    qdd = np.zeros_like(q)
    for j in range(q.shape[1]):
        spline = make_smoothing_spline(t, q[:, j], lam=1e-4)
        qd[:, j] = spline.derivative(1)(t)
        qdd[:, j] = spline.derivative(2)(t)
    rotations, origin_rows = [], []
    for k in range(len(t)):
        for name in ik_names[1:]:
            if coords.contains(name):
                coords.get(name).setValue(state, float(ik[k, ik_names.index(name)]), False)
        model.realizePosition(state)
        transform = root.getTransformInGround(state)
        rot = transform.R()
        rotations.append(np.array([[rot.get(i, j) for j in range(3)] for i in range(3)]))
        origin_rows.append(np.array(transform.p().to_numpy()))
    origins = np.array(origin_rows)
    # the root's linear acceleration enters as a fictitious force: effective gravity g - a_root
    accel = np.stack([make_smoothing_spline(t, origins[:, i], lam=1e-4).derivative(2)(t) for i in range(3)], axis=1)
    pack_rows, gravities = [], []
    for k in range(len(t)):
        r = rotations[k]
        g = r.T @ (g_world - (accel[k] if include_root_acceleration else 0.0))
        gravities.append(g)
        pack_rows.append(
            pack.inverse_dynamics(q[k], qd[k], qdd[k], hand_load_newton, gravity=g, out_of_range=OutOfRange.CLAMP)
        )
    pack_tau = np.array(pack_rows)
    id_t = idd[:, 0] - ik[0, 0]
    recorded = np.stack([np.interp(t, id_t, idd[:, id_names.index(c)]) for c in pack.coordinates], axis=1)
    err = pack_tau - recorded
    peak = np.max(np.abs(recorded), axis=0)
    return {
        "frames": len(t),
        "peak_nm": dict(zip(pack.coordinates, peak.tolist())),
        "rms_error_nm": dict(zip(pack.coordinates, np.sqrt(np.mean(err**2, axis=0)).tolist())),
        "max_error_nm": dict(zip(pack.coordinates, np.max(np.abs(err), axis=0).tolist())),
        "rms_error_percent_of_peak": dict(
            zip(pack.coordinates, (100 * np.sqrt(np.mean(err**2, axis=0)) / peak).tolist())
        ),
        "correlation": dict(
            zip(
                pack.coordinates,
                [float(np.corrcoef(pack_tau[:, j], recorded[:, j])[0, 1]) for j in range(len(pack.coordinates))],
            )
        ),
        "time": t,
        "pack": pack_tau,
        "recorded": recorded,
    }

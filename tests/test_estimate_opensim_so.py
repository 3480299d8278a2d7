"""`so` reproduces OpenSim's own StaticOptimization tool on the arm26 tutorial inputs (physiology off: F = F_max a)."""

from __future__ import annotations

import numpy as np
import pytest

from msk_core.estimate import FrameEstimator
from msk_core.estimate.reference import opensim_filtered_kinematics, run_opensim_static_optimization
from msk_core.io import read_sto

opensim = pytest.importorskip("opensim")

COORDS = ["r_shoulder_elev", "r_elbow_flex"]


class OpenSimMomentArms:
    """Moment arms straight from OpenSim's computeMomentArm: checks the estimator alone, without any surrogate."""

    name, version = "opensim-arm26", "reference"
    coordinates = COORDS

    def __init__(self, osim_path) -> None:
        self.model = opensim.Model(str(osim_path))
        self.state = self.model.initSystem()
        muscles = self.model.getMuscles()
        self.muscles = [muscles.get(i) for i in range(muscles.getSize())]
        self.groups = [m.getName() for m in self.muscles]
        self.f_max_ref = np.array([m.getMaxIsometricForce() for m in self.muscles])
        self.coords = [self.model.getCoordinateSet().get(c) for c in COORDS]

    def moment_arms(self, q):
        for c, v in zip(self.coords, q):
            c.setValue(self.state, float(v), False)
        self.model.realizePosition(self.state)
        return np.array([[m.computeMomentArm(self.state, c) for m in self.muscles] for c in self.coords])

    def inverse_dynamics(self, q, qd, qdd, hand_load_newton):
        raise AssertionError("torques are given explicitly in this test")


@pytest.fixture(scope="module")
def arm26(shared_dir, tmp_path_factory):
    data = shared_dir / "data" / "opensim-arm26"
    model = shared_dir / "models" / "arm26.osim"
    ref = run_opensim_static_optimization(
        data / "arm26_Setup_StaticOptimization.xml",
        model,
        data / "arm26_InverseKinematics.mot",
        tmp_path_factory.mktemp("opensim_so"),
        use_muscle_physiology=False,
    )
    times = ref.activations.time
    q, qd, qdd = opensim_filtered_kinematics(model, data / "arm26_InverseKinematics.mot", COORDS, times, 6.0)
    # OpenSim's ID of the same filtered motion (the tutorial file) is the torque SO had to match.
    id_sto = read_sto(data / "arm26_InverseDynamics.sto")
    torques = id_sto.select([f"{c}_moment" for c in COORDS])
    assert id_sto.n_rows == len(times) and np.allclose(id_sto.time, times, atol=1e-6)
    return {"ref": ref, "q": q, "qd": qd, "qdd": qdd, "torques": torques, "model": model}


def _run_so(pack, arm26):
    muscles = list(arm26["ref"].activations.columns)
    assert list(pack.groups) == muscles
    a_min = np.array([arm26["ref"].min_control[m] for m in muscles])  # OpenSim bounds SO by each muscle's min_control
    est = FrameEstimator(pack, method="so", a_min=a_min)
    out = np.array([est.step(q, torques=t).activations for q, t in zip(arm26["q"], arm26["torques"])])
    return out, est


def test_so_reproduces_opensim_static_optimization_with_opensim_moment_arms(arm26):
    out, est = _run_so(OpenSimMomentArms(arm26["model"]), arm26)
    ref = arm26["ref"].activations.data
    rms = float(np.sqrt(np.mean((out - ref) ** 2)))
    assert est.flag_counts == {}
    assert rms <= 0.01, rms
    assert np.abs(out - ref).max() < 0.02
    # Non-trivial: OpenSim's activations vary over the motion, so matching them is not matching a constant.
    assert ref.std(axis=0).max() > 0.02


def test_so_reproduces_opensim_static_optimization_with_the_arm26_pack(arm26):
    from msk_core.model import load_pack

    pack = load_pack("arm26")
    out, est = _run_so(pack, arm26)
    ref = arm26["ref"].activations.data
    rms = float(np.sqrt(np.mean((out - ref) ** 2)))
    assert rms <= 0.01, rms
    # And with the pack's own inverse dynamics (surrogate ID instead of OpenSim's ID file).
    est = FrameEstimator(pack, method="so", a_min=0.01)
    out_id = np.array([est.step(q, qd, qdd).activations for q, qd, qdd in zip(arm26["q"], arm26["qd"], arm26["qdd"])])
    assert float(np.sqrt(np.mean((out_id - ref) ** 2))) <= 0.01

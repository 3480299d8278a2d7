"""IMU kinematics: static sensor-to-segment alignment, joint-angle convention, Kalman filter and RTS smoother."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from msk_core.errors import ConfigError, InputError
from msk_core.imu.kinematics import (
    JointKinematicsFilter,
    KinematicsFilterConfig,
    joint_angles,
    npose_segment_orientation,
    segment_orientation,
    sensor_to_segment,
    smooth_kinematics,
)

FS = 100.0


def _session(heading: float, seed: int):
    """Upper arm and forearm: 1 s static N-pose, then elbow flexion 0..120 deg with some pronation-free
    ab/adduction of the shoulder. Sensors strapped on with arbitrary unknown rotations. Returns sensor quaternions
    (w, x, y, z) and the true elbow angles."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(6 * FS)) / FS
    moving = t >= 1.0
    flex = np.where(moving, np.radians(60.0) * (1 - np.cos(2 * np.pi * 0.5 * (t - 1.0))), 0.0)
    abd = np.where(moving, np.radians(20.0) * np.sin(2 * np.pi * 0.3 * (t - 1.0)), 0.0)
    base = npose_segment_orientation(heading)
    # upper arm swings in the sagittal plane and abducts; forearm adds elbow flexion about the upper arm's Z
    upper = base * Rotation.from_euler("ZX", np.column_stack([0.5 * flex, abd]))
    fore = upper * Rotation.from_euler("Z", flex[:, None])
    mounts = [Rotation.random(random_state=int(rng.integers(1 << 30))) for _ in range(2)]  # R_SB, unknown to us
    noise = [Rotation.from_rotvec(np.radians(0.2) * rng.standard_normal((t.shape[0], 3))) for _ in range(2)]
    q_upper = (upper * mounts[0].inv() * noise[0]).as_quat(scalar_first=True)
    q_fore = (fore * mounts[1].inv() * noise[1]).as_quat(scalar_first=True)
    return t, q_upper, q_fore, flex


@pytest.mark.parametrize("heading", [0.0, 1.2])
def test_static_alignment_recovers_elbow_flexion(heading: float) -> None:
    t, q_upper, q_fore, flex = _session(heading, seed=int(heading * 10))
    static = t < 1.0
    r_upper = sensor_to_segment(q_upper[static], heading_rad=heading)
    r_fore = sensor_to_segment(q_fore[static], heading_rad=heading)
    ang = joint_angles(segment_orientation(q_upper, r_upper), segment_orientation(q_fore, r_fore))
    assert np.degrees(np.max(np.abs(ang[:, 0] - flex))) < 1.5
    assert np.degrees(np.max(np.abs(ang[:, 1:]))) < 1.5  # no elbow ab/adduction or rotation
    # with the wrong heading the static pose is misread: the error shows up in the angles
    r_wrong = sensor_to_segment(q_upper[static], heading_rad=heading + 0.5)
    wrong = joint_angles(segment_orientation(q_upper, r_wrong), segment_orientation(q_fore, r_fore))
    assert np.degrees(np.max(np.abs(wrong - ang))) > 10.0


def test_angle_convention() -> None:
    parent = npose_segment_orientation(0.3)
    ang = joint_angles(parent, parent * Rotation.from_euler("Z", np.radians(90.0)))
    np.testing.assert_allclose(np.degrees(ang[0]), [90.0, 0.0, 0.0], atol=1e-9)
    # flexion of a segment hanging down (Y up) swings its distal end forward (+X anterior in the N-pose)
    child = parent * Rotation.from_euler("Z", np.radians(30.0))
    distal = child.apply([0.0, -1.0, 0.0])
    forward = npose_segment_orientation(0.3).apply([1.0, 0.0, 0.0])
    assert np.dot(distal, forward) > 0.49
    ang = joint_angles(parent, parent * Rotation.from_euler("ZXY", np.radians([40.0, -15.0, 25.0])))
    np.testing.assert_allclose(np.degrees(ang[0]), [40.0, -15.0, 25.0], atol=1e-9)


def test_static_pose_must_be_static() -> None:
    q = Rotation.from_euler("z", np.linspace(0, 1.0, 50)[:, None]).as_quat(scalar_first=True)
    with pytest.raises(InputError, match="moved during the static pose"):
        sensor_to_segment(q)
    with pytest.raises(InputError, match="non-zero"):
        sensor_to_segment(np.zeros((3, 4)))


def _trajectory():
    t = np.arange(int(8 * FS)) / FS
    w = 2 * np.pi * 0.4
    angle = np.column_stack([1.0 * np.sin(w * t), 0.3 * np.cos(2 * w * t)])
    vel = np.column_stack([w * np.cos(w * t), -0.6 * w * np.sin(2 * w * t)])
    acc = np.column_stack([-w * w * np.sin(w * t), -1.2 * w * w * np.cos(2 * w * t)])
    return t, angle, vel, acc


def test_kalman_filter_is_causal_and_estimates_derivatives() -> None:
    t, angle, vel, acc = _trajectory()
    noise_std = np.radians(1.0)
    z = angle + noise_std * np.random.default_rng(0).standard_normal(angle.shape)
    cfg = KinematicsFilterConfig(dt=1 / FS, jerk_std=50.0, angle_std=noise_std)
    a, v, ac = JointKinematicsFilter(2, cfg).filter(z)
    sl = slice(int(FS), None)  # after convergence
    rms = lambda e: float(np.sqrt(np.mean(e[sl] ** 2)))  # noqa: E731
    assert rms(a - angle) < 0.7 * noise_std
    naive_vel = np.gradient(z, 1 / FS, axis=0)
    assert rms(v - vel) < 0.25 * rms(naive_vel - vel)
    assert rms(v - vel) < 0.3  # rad/s on a 2.5 rad/s motion (the causal lag dominates)
    naive_acc = np.gradient(naive_vel, 1 / FS, axis=0)
    assert rms(ac - acc) < 0.05 * rms(naive_acc - acc)
    # causal: the first k outputs do not change when later samples are removed
    k = 300
    a_k, v_k, _ = JointKinematicsFilter(2, cfg).filter(z[:k])
    np.testing.assert_array_equal(a_k, a[:k])
    np.testing.assert_array_equal(v_k, v[:k])
    # offline RTS smoother of the same model beats the causal filter
    sa, sv, sac = smooth_kinematics(z, cfg)
    assert rms(sa - angle) < rms(a - angle)
    assert rms(sv - vel) < 0.7 * rms(v - vel)
    assert rms(sac - acc) < rms(ac - acc)


def test_kalman_variable_dt_and_gaps() -> None:
    t, angle, vel, _ = _trajectory()
    cfg = KinematicsFilterConfig(dt=1 / FS, jerk_std=50.0, angle_std=np.radians(0.5))
    f = JointKinematicsFilter(2, cfg)
    keep = np.ones(t.shape[0], dtype=bool)
    keep[200:230] = False  # dropped samples: a longer dt across the gap
    ts = t[keep]
    out = [f.step(angle[i], dt=(ts[j] - ts[j - 1]) if j else None) for j, i in enumerate(np.flatnonzero(keep))]
    v = np.array([o[1] for o in out])
    # once the gap is behind, the estimate is back on the uninterrupted filter's track
    _, v_full, _ = JointKinematicsFilter(2, cfg).filter(angle)
    np.testing.assert_allclose(v[300:], v_full[keep][300:], atol=0.02)
    assert np.max(np.abs(v - v_full[keep])) < 0.5
    g = JointKinematicsFilter(2, cfg)
    g.step(angle[0])
    a_nan, _, _ = g.step(np.array([np.nan, np.nan]))  # missing sample: predicted only
    assert np.all(np.isfinite(a_nan))
    with pytest.raises(ConfigError, match="dt"):
        KinematicsFilterConfig(dt=0.0)
    with pytest.raises(InputError, match="expected 2 angles"):
        g.step(np.zeros(3))


def _real_xsens_quats(shared_dir, k: int) -> np.ndarray:
    """Orientation of a real, resting MTi-G-710 (Euler roll/pitch/yaw in degrees, Xsens R = Rz Ry Rx)."""
    from drivers.xsens.xbus import decode_mtdata2, iter_capture

    raw = (shared_dir / f"data/xsens-captures/mtig710_set{k}.bin").read_bytes()
    euler = [decode_mtdata2(m.data).get("euler") for m in iter_capture(raw) if m.mid == 0x36]
    e = np.array([x for x in euler if x is not None])
    return Rotation.from_euler("xyz", e, degrees=True).as_quat(scalar_first=True)


@pytest.mark.parametrize("k", [1, 4])
def test_real_xsens_orientation_through_alignment_and_filter(shared_dir, k: int) -> None:
    q = _real_xsens_quats(shared_dir, k)
    assert q.shape[0] >= 90
    r_sb = sensor_to_segment(q[:40])  # the sensor rests: real noise passes the static check
    seg = segment_orientation(q, r_sb)
    drift = np.degrees((npose_segment_orientation(0.0).inv() * seg).magnitude())
    assert drift.max() < 1.0  # the calibrated segment stays in the N-pose over the whole capture
    # a joint between two segments both carried by this sensor is at zero
    np.testing.assert_allclose(joint_angles(seg, seg), 0.0, atol=1e-9)
    # filtering the real (static) angles shrinks their sample-to-sample noise (the slow drift is kept)
    ang = joint_angles(npose_segment_orientation(0.0), seg)
    cfg = KinematicsFilterConfig(dt=0.01, jerk_std=5.0, angle_std=np.radians(0.2))
    a, v, _ = JointKinematicsFilter(3, cfg).filter(ang)
    assert np.all(np.std(np.diff(a[20:], axis=0), axis=0) < 0.7 * np.std(np.diff(ang[20:], axis=0), axis=0))
    assert np.all(np.abs(v[20:]) < np.radians(10.0))


def test_sensor_calibration_for_several_joints_round_trips_json() -> None:
    import json

    from msk_core.imu.kinematics import Joint, SensorCalibration

    t, q_upper, q_fore, flex = _session(0.7, seed=5)
    static = t < 1.0
    cal = SensorCalibration.from_static_pose({"upper_arm": q_upper[static], "forearm": q_fore[static]}, heading_rad=0.7)
    back = SensorCalibration.from_dict(json.loads(json.dumps(cal.to_dict())))
    joints = [Joint("elbow", "upper_arm", "forearm")]
    angles = back.joint_angles({"upper_arm": q_upper, "forearm": q_fore}, joints)
    assert np.degrees(np.max(np.abs(angles["elbow"][:, 0] - flex))) < 1.5
    with pytest.raises(InputError, match="joint 'wrist' needs segment 'forearm'"):
        cal.joint_angles({"upper_arm": q_upper}, [Joint("wrist", "forearm", "hand")])
    moving = Rotation.from_euler("z", np.linspace(0, 1.0, 50)[:, None]).as_quat(scalar_first=True)
    with pytest.raises(InputError, match="segment 'forearm'.*moved"):
        SensorCalibration.from_static_pose({"upper_arm": q_upper[static], "forearm": moving})


def test_quaternion_twist_equals_the_rotation_one() -> None:
    """The kinematics node's quaternion path (ImuJointMapper.angles) gives Rotation's composition and twist."""
    from msk_core.imu.kinematics import quat_product, twist_angle, twist_angle_quats, unit_quats

    rng = np.random.default_rng(5)
    a, b = Rotation.random(200, random_state=1), Rotation.random(200, random_state=2)
    qa, qb = a.as_quat(scalar_first=True), b.as_quat(scalar_first=True)
    composed = quat_product(qa, qb)
    expected = (a * b).as_quat(scalar_first=True)
    assert np.allclose(np.abs(np.sum(composed * expected, axis=1)), 1.0, atol=1e-12)  # same rotation (q or -q)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    got = twist_angle_quats(unit_quats(qa * 3.0), qb, axis)
    assert np.allclose(np.angle(np.exp(1j * (got - twist_angle(a, b, axis)))), 0.0, atol=1e-12)
    with pytest.raises(InputError, match="finite and non-zero"):
        unit_quats(np.array([np.nan, 0.0, 0.0, 1.0]))

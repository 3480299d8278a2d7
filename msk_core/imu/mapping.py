"""Which IMU segments give which model coordinates: one small declarative table per pack, static calibration, angles.

A pack's table (:data:`MAPPINGS`) lists one :class:`HingeMap` per pack coordinate: the ``child`` segment turns
relative to the ``parent`` segment about ``axis`` (a unit vector in the parent's body frame) by
``gain * (q - q_reference)``. Body frames are the pack's (``msk_core.model.rigid``): every body frame is aligned with
the model's ground (X anterior, Y up, Z right) at the pack's reference pose, so the axes are the pack joints' axes.
``world`` is a virtual segment fixed to the ground (the floor under a planted foot, the bench under the torso):
its orientation is the model ground's, from the subject's heading and the pack's gravity. Docs: docs/kinematics.md.

Static calibration: during a window in which the subject holds a known pose ``q0`` (the table's ``static_pose_deg``
unless given), every segment's body orientation follows from the table (down the tree from ``world``), and each
sensor's fixed sensor-to-segment rotation is ``R_SB = mean(R_GS)^T R_GB(q0)``
(:func:`msk_core.imu.kinematics.sensor_to_segment`). Live, ``q = q_reference + twist(R_parent^T R_child, axis)/gain``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from msk_core.errors import ConfigError, InputError
from msk_core.imu.kinematics import (
    SensorCalibration,
    model_ground_orientation,
    quat_product,
    sensor_to_segment,
    twist_angle_quats,
    unit_quats,
)

WORLD = "world"


@dataclass(frozen=True)
class HingeMap:
    """One pack coordinate from one segment pair: ``R_parent^T R_child = Rot(axis, gain * (q - q_ref))``."""

    coordinate: str
    parent: str
    child: str
    axis: tuple[float, float, float]  # unit vector in the parent segment's body frame
    gain: float = 1.0  # body rotation per unit coordinate (e.g. 5 when one coordinate drives 5 spinal levels)

    def __post_init__(self) -> None:
        a = np.asarray(self.axis, dtype=float)
        if a.shape != (3,) or abs(np.linalg.norm(a) - 1.0) > 1e-2:
            raise ConfigError("hinge axis must be a unit 3-vector", field=f"{self.coordinate}.axis", value=self.axis)
        if not (np.isfinite(self.gain) and self.gain != 0.0):
            raise ConfigError("gain must be finite and non-zero", field=f"{self.coordinate}.gain", value=self.gain)
        if self.parent == self.child:
            raise ConfigError("parent and child must differ", field=f"{self.coordinate}.child", value=self.child)

    @property
    def unit_axis(self) -> np.ndarray:
        a = np.asarray(self.axis, dtype=float)
        return a / np.linalg.norm(a)


@dataclass(frozen=True)
class PackMapping:
    """The IMU-to-coordinate table of one pack; segments other than ``world`` each carry one tracker."""

    pack: str
    hinges: tuple[HingeMap, ...]
    static_pose_deg: Mapping[str, float] = field(default_factory=dict)  # calibration pose (the synth's start pose)

    @property
    def coordinates(self) -> list[str]:
        return [h.coordinate for h in self.hinges]

    @property
    def segments(self) -> list[str]:
        """Instrumented segments in table order (``world`` excluded)."""
        out: list[str] = []
        for h in self.hinges:
            for s in (h.parent, h.child):
                if s != WORLD and s not in out:
                    out.append(s)
        return out


# Axes: the packs' joint axes (pack.rigid.description["joints"][j]["axis"]), rounded; tests/test_kinematics_node.py
# checks they still agree with the shipped packs. Static poses: the first pose of every msk_core.synth trial.
MAPPINGS: dict[str, PackMapping] = {
    "bench_press": PackMapping(
        pack="bench_press",
        hinges=(
            # torso on the bench (welded to ground in the pack): shoulder flexion is the upper arm against the world
            HingeMap("elv_angle_r", WORLD, "upper_arm_r", (0.005, 0.042, 0.999)),
            HingeMap("elbow_flex_r", "upper_arm_r", "forearm_r", (0.226, 0.022, 0.974)),  # carrying-angle tilt
        ),
        static_pose_deg={"elv_angle_r": 85.0, "elbow_flex_r": 15.0},
    ),
    "deadlift": PackMapping(
        pack="deadlift",
        hinges=(
            # the synth's torso tracker sits on lumbar1: five of the six levels L5_S1_FE drives (a sternum tracker: 6)
            HingeMap("L5_S1_FE", "pelvis", "torso", (0.0, 0.0, 1.0), gain=5.0),
            HingeMap("hip_flexion_r", "pelvis", "thigh_r", (0.0, 0.0, 1.0)),
            # Lai/Walker rolling knee: the femur turns about the tibia's Z by ~knee_angle_r (plus <10 deg of
            # ab/adduction and rotation, which the twist ignores); the shank therefore turns by -knee about the thigh
            HingeMap("knee_angle_r", "thigh_r", "shank_r", (0.0, 0.0, 1.0), gain=-1.0),
            # foot flat on the floor (no foot tracker needed): the ankle is the shank against the world
            HingeMap("ankle_angle_r", WORLD, "shank_r", (0.105, 0.174, -0.979)),
        ),
        # knee 4 deg: the synth keeps 4 deg inside the pack's fitted knee range [0, 120] deg
        static_pose_deg={"L5_S1_FE": 0.0, "hip_flexion_r": 0.0, "knee_angle_r": 4.0, "ankle_angle_r": 4.0},
    ),
}


def mapping_for(pack_name: str) -> PackMapping:
    mapping = MAPPINGS.get(pack_name)
    if mapping is None:
        raise ConfigError(
            f"no IMU mapping for pack {pack_name!r}; tables exist for {sorted(MAPPINGS)}", field="pack", value=pack_name
        )
    return mapping


def parse_pose(text: str, coordinates: list[str]) -> dict[str, float]:
    """``"elv_angle_r=85,elbow_flex_r=15"`` (degrees) -> {name: deg}; every name must be a coordinate."""
    out: dict[str, float] = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        name, sep, value = part.partition("=")
        if not sep:
            raise ConfigError("expected NAME=DEGREES", field="static pose", value=part)
        if name.strip() not in coordinates:
            raise ConfigError(f"unknown coordinate; the pack has {coordinates}", field="static pose", value=name)
        try:
            out[name.strip()] = float(value)
        except ValueError:
            raise ConfigError("not a number (degrees)", field=name.strip(), value=value) from None
    return out


class ImuJointMapper:
    """Pack coordinates from calibrated segment orientations, following one :class:`PackMapping`.

    State: the :class:`SensorCalibration` (``None`` until :meth:`calibrate`)."""

    def __init__(
        self,
        mapping: PackMapping,
        *,
        coordinates: list[str],
        reference_pose: np.ndarray,
        gravity: np.ndarray,
        heading_rad: float,
    ) -> None:
        missing = [c for c in coordinates if c not in mapping.coordinates]
        extra = [c for c in mapping.coordinates if c not in coordinates]
        if missing or extra:
            raise ConfigError(
                f"IMU mapping {mapping.pack!r} does not match the pack: missing {missing}, unknown {extra}",
                field="pack",
                value=mapping.pack,
            )
        by_name = {h.coordinate: h for h in mapping.hinges}
        self.mapping = mapping
        self.coordinates = list(coordinates)
        self.hinges = [by_name[c] for c in coordinates]  # pack order
        self.reference_pose = np.asarray(reference_pose, dtype=float)
        self.ground = model_ground_orientation(gravity, heading_rad)
        self.heading_rad = float(heading_rad)
        self.segments = mapping.segments
        self.calibration: SensorCalibration | None = None
        self._order = _tree_order(mapping.hinges)
        self._ground_quat = self.ground.as_quat(scalar_first=True).reshape(4)
        self._axes = [h.unit_axis for h in self.hinges]
        self._quats: dict[str, np.ndarray] = {}
        self._quats_of: SensorCalibration | None = None

    @classmethod
    def for_pack(cls, pack, *, heading_rad: float, mapping: PackMapping | None = None) -> ImuJointMapper:
        return cls(
            mapping or mapping_for(pack.name),
            coordinates=list(pack.coordinates),
            reference_pose=pack.reference_pose,
            gravity=pack.rigid.gravity,
            heading_rad=heading_rad,
        )

    def static_pose(self, pose_deg: Mapping[str, float] | None = None) -> np.ndarray:
        """The calibration pose (rad, pack order): the table's, overridden by ``pose_deg``; all coordinates needed."""
        merged = {**self.mapping.static_pose_deg, **(pose_deg or {})}
        missing = [c for c in self.coordinates if c not in merged]
        if missing:
            raise ConfigError(f"the static pose lacks {missing}", field="static pose")
        return np.radians([merged[c] for c in self.coordinates])

    def segment_orientations(self, q: np.ndarray) -> dict[str, Rotation]:
        """Global orientation ``R_GB`` of every segment (and ``world``) at pose ``q`` (rad, pack order)."""
        q = np.asarray(q, dtype=float)
        out = {WORLD: self.ground}
        for k, forward in self._order:
            h = self.mapping.hinges[k]
            i = self.coordinates.index(h.coordinate)
            turn = Rotation.from_rotvec(h.unit_axis * h.gain * (q[i] - self.reference_pose[i]))
            if forward:
                out[h.child] = out[h.parent] * turn
            else:
                out[h.parent] = out[h.child] * turn.inv()
        return out

    def calibrate(self, static_quats: Mapping[str, np.ndarray], q0: np.ndarray) -> SensorCalibration:
        """Sensor-to-segment rotations from each segment's quaternions ``(n, 4)`` during the static pose ``q0``."""
        known = self.segment_orientations(q0)
        out = {}
        for segment in self.segments:
            if segment not in static_quats:
                raise InputError(f"no samples of segment {segment!r} in the static window", field=segment)
            try:
                out[segment] = sensor_to_segment(static_quats[segment], segment_orientation=known[segment])
            except InputError as exc:
                raise InputError(f"segment {segment!r}: {exc}", field=segment) from None
        self.calibration = SensorCalibration(out, self.heading_rad)
        return self.calibration

    def angles(self, quats: Mapping[str, np.ndarray]) -> np.ndarray:
        """Pack coordinates (rad) ``(n, n_coordinates)`` from every segment's sensor quaternions ``(n, 4)``."""
        if self.calibration is None:
            raise ConfigError("the IMU mapping is not calibrated yet", field="calibration")
        # quaternion arithmetic, not Rotation objects: the same twist angles (within 1e-13 rad), cheaper
        to_segment = self._calibration_quats()
        seg = {WORLD: self._ground_quat}
        for segment in self.segments:
            if segment not in quats:
                raise InputError(f"no sample of segment {segment!r}", field=segment)
            seg[segment] = quat_product(unit_quats(quats[segment]), to_segment[segment])
        n = len(np.atleast_2d(quats[self.segments[0]]))
        out = np.empty((n, len(self.coordinates)))
        for i, (h, axis) in enumerate(zip(self.hinges, self._axes)):
            out[:, i] = self.reference_pose[i] + twist_angle_quats(seg[h.parent], seg[h.child], axis) / h.gain
        return out

    def _calibration_quats(self) -> dict[str, np.ndarray]:
        """The calibration's sensor-to-segment rotations as scalar-first quaternions (kept until it changes)."""
        calibration = self.calibration
        assert calibration is not None
        if self._quats_of is not calibration:
            self._quats = {s: r.as_quat(scalar_first=True).reshape(4) for s, r in calibration.sensor_to_segment.items()}
            self._quats_of = calibration
        return self._quats


def _tree_order(hinges: tuple[HingeMap, ...]) -> list[tuple[int, bool]]:
    """Hinges in breadth-first order from ``world``: (index, True when the parent is the known side)."""
    known, order, pending = {WORLD}, [], list(range(len(hinges)))
    while pending:
        progressed = False
        for k in list(pending):
            h = hinges[k]
            if h.parent in known or h.child in known:
                order.append((k, h.parent in known))
                known.update((h.parent, h.child))
                pending.remove(k)
                progressed = True
        if not progressed:
            names = sorted({s for k in pending for s in (hinges[k].parent, hinges[k].child)})
            raise ConfigError(f"segments {names} are not connected to {WORLD!r} through the hinges", field="hinges")
    return order
